"""Why a saved SB3 or skrl policy stalls: its deterministic episodes stage by stage, its actions, and its critic
against the return it realises. A probe of issue 91's "one probe of why" for a library cell below 20 % success.

    PYTHONPATH=. .venv/bin/python -m scripts.diagnose_policy --model runs/.../model.zip \\
        --vecnormalize runs/.../vecnormalize.pkl --episodes 10 --out runs/diagnose/td3.json
    PYTHONPATH=. .venv/bin/python -m scripts.diagnose_policy --skrl-cell state/GraspLift/skrl-ppo-tuned/s3 \\
        --model runs/full/state__GraspLift__skrl-ppo-tuned__s3/agent.pt --episodes 10

A skrl PPO cell's agent (``--skrl-cell``, from state) is rebuilt from the cell's config by ``benchmarks.algorithms``'
own loader and scales its observations itself; its critic is ``V(s)``.

Episodes are played as ``benchmarks.algorithms --validate`` plays them (one CPU env, the observation normalised
with the saved ``VecNormalize``'s ``normalize_obs``, ``predict(deterministic=True)``), on validation seeds
(``agents.common.VALIDATION_SEED`` onwards by default), never the held-out ones. Per episode and step it records:

- **stages**, from the task's ``info`` events: ``grasped``, ``lifted`` (grasped and lifted), ``holding`` (grasped,
  lifted and still: ``hold_steps`` > 0) and ``success``; a task without an event never reaches that stage. The
  table gives each stage's share of episodes and its first step (1-based, mean over the episodes that reach it).
- **actions** in the stage the step starts from: the share of arm components (all but the last) and of the gripper
  component at the bound (``|a| > 0.99``), the share of steps commanding the gripper closed (``a <= 0``), and the
  tool's speed (m/s, from the TCP position a control step apart).
- **bootstrapping**: the critic's value of the policy's own action, ``Q(s, pi(s))`` (the smaller of an off-policy
  learner's twin critics, as its target takes; ``V(s)`` for PPO), against the discounted return the episode
  realised from that step with the learner's gamma. ``--absorbing-bonus`` (default on, as the configs' wrapper
  ``AbsorbingSuccess``) adds ``gamma / (1 - gamma)`` to the reward of a step whose success ends the episode. A
  step fewer than ``horizon`` steps before a time-limit truncation is left out of the comparison: its realised
  return is cut short (``horizon``: where ``gamma ** k`` falls below 1 %).

``--action-noise SIGMA`` and ``--stochastic`` play the policy as it acts while training instead: its deterministic
action plus Gaussian noise of that σ per component, clipped to the bounds (SB3's ``NormalActionNoise`` as TD3 and
DDPG explore; drawn from a generator seeded with the episode's seed), or a sample of its own distribution
(``predict(deterministic=False)``: PPO's Gaussian, SAC's squashed one; torch seeded with the episode's seed). Both
ask why a learner whose deterministic policy succeeds never succeeds in its training episodes.

``--replay`` (a replay buffer saved by ``save_replay_buffer``) adds what training saw: its transitions by reward
stage (``floor(reward * 4)`` under ``normalized_dense``), the lifted ones that paid at least a still step's reward
(GraspLift's settle term at 2 cm/s), the arm's actions in those, and how many carried the absorbing bonus.

Prints the per-stage table and writes everything to ``--out`` as JSON. Bad input (a missing file, a count below 1,
an unknown env id) is one line on stderr and exit status 2, before any env is built.
"""

from __future__ import annotations

import json
import math
import pickle
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

if TYPE_CHECKING:
    import torch

STAGES = ("reach", "grasped", "lifted", "holding", "success")
"""the stage a step starts from, in order; the first is every episode's start"""
SATURATED = 0.99
EXTRA = ("ik_unreachable", "object_speed", "object_height")
"""the task's per-step ``info`` values averaged per stage as well (nan where a task has none)"""
ALGOS = ("ppo", "sac", "td3", "ddpg")


@dataclass
class Args:
    model: Path
    """an SB3 model.zip; with --skrl-cell, the cell's skrl agent.pt (or its selected best/best_agent.pt)"""
    skrl_cell: Optional[str] = None
    """the benchmarks.algorithms cell the skrl --model comes from (e.g. state/GraspLift/skrl-ppo-tuned/s3): its
    config builds the agent that loads it"""
    vecnormalize: Optional[Path] = None
    """the VecNormalize the model was trained with (a pickle without its envs, as SB3's ``save`` writes it)"""
    env_id: str = "GraspLift-IRB120-v1"
    """the task"""
    episodes: int = 10
    """episodes, one a seed (deterministic unless --action-noise or --stochastic)"""
    first_seed: int = 20_000_000
    """the first episode's seed (validation seeds: agents.common.VALIDATION_SEED)"""
    max_steps: Optional[int] = None
    """end an episode after this many steps (a truncation), short of the task's own limit"""
    algo: Optional[str] = None
    """the SB3 class (ppo, sac, td3, ddpg); default: read from the zip"""
    gamma: Optional[float] = None
    """the discount of the realised return; default: the model's"""
    absorbing_bonus: bool = True
    """add gamma / (1 - gamma) to a success that ends the episode (the configs' AbsorbingSuccess wrapper)"""
    action_noise: float = 0.0
    """σ of Gaussian noise added to each action component, then clipped to [-1, 1] (TD3's and DDPG's training
    exploration); 0: none"""
    stochastic: bool = False
    """sample the policy's own distribution (predict(deterministic=False)), as PPO and SAC act in training"""
    replay: Optional[Path] = None
    """a replay buffer the model saved (save_replay_buffer), to count what training saw"""
    out: Path = Path("runs/diagnose_policy/diagnosis.json")
    """the JSON written"""


def model_algo(path: Path) -> str:
    """The SB3 algorithm a model.zip holds, from its policy class's module (``stable_baselines3.td3.policies``)."""
    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
        module = data["policy_class"]["__module__"]
    except (zipfile.BadZipFile, KeyError, ValueError) as e:
        raise ValueError(f"--model {path} is not an SB3 model.zip ({e}); or give --algo") from None
    algo = module.split(".")[1] if module.startswith("stable_baselines3.") else ""
    if algo not in ALGOS:
        raise ValueError(f"--model {path}: policy class from {module!r}, not one of SB3's {', '.join(ALGOS)}; --algo")
    return algo


def check(args: Args) -> None:
    for flag, path in (("--model", args.model), ("--vecnormalize", args.vecnormalize), ("--replay", args.replay)):
        if path is not None and not Path(path).is_file():
            raise FileNotFoundError(f"{flag} {path} does not exist")
    if args.episodes < 1:
        raise ValueError(f"--episodes {args.episodes}: give a whole number >= 1")
    if args.first_seed < 0:
        raise ValueError(f"--first-seed {args.first_seed}: seeds are 0 or more")
    if args.max_steps is not None and args.max_steps < 1:
        raise ValueError(f"--max-steps {args.max_steps}: give a whole number >= 1")
    if args.gamma is not None and not 0.0 <= args.gamma < 1.0:
        raise ValueError(f"--gamma {args.gamma}: give a discount in [0, 1)")
    if not math.isfinite(args.action_noise) or args.action_noise < 0:
        raise ValueError(f"--action-noise {args.action_noise}: give a standard deviation >= 0")
    if args.action_noise > 0 and args.stochastic:
        raise ValueError("--action-noise with --stochastic: give one way to explore, not both")
    if args.algo is not None and args.algo not in ALGOS:
        raise ValueError(f"--algo {args.algo!r}: one of {', '.join(ALGOS)}")
    if args.skrl_cell is not None:
        from benchmarks.algorithms import ALGORITHMS, parse_cell

        obs, task, algo, _ = parse_cell(args.skrl_cell)
        if ALGORITHMS[algo].runner != "skrl" or not algo.startswith("skrl-ppo") or obs != "state":
            raise ValueError(f"--skrl-cell {args.skrl_cell}: not a skrl PPO cell from state (its critic is V(s))")
        if args.vecnormalize is not None or args.replay is not None or args.algo is not None:
            raise ValueError("--skrl-cell: the agent scales its own observations; no --vecnormalize, --replay, --algo")
        if args.stochastic:
            raise ValueError("--skrl-cell: --stochastic samples SB3 policies only; --action-noise works for both")
    else:
        algo = args.algo or model_algo(args.model)
        if args.stochastic and algo in ("td3", "ddpg"):
            raise ValueError(f"--stochastic: {algo}'s actor is deterministic; --action-noise plays its exploration")
    from maniskill_irb120.envs import check_env_id

    check_env_id(args.env_id)


def step_stage(info: dict) -> int:
    """The index in :data:`STAGES` of the state ``info`` (one env's events) describes."""

    def event(key: str) -> bool:
        v = info.get(key)
        return v is not None and bool(np.asarray(v).reshape(-1)[0])

    grasped, lifted = event("grasped"), event("lifted")
    holding = grasped and lifted and int(np.asarray(info.get("hold_steps", 0)).reshape(-1)[0]) > 0
    return 4 if event("success") else 3 if holding else 2 if grasped and lifted else 1 if grasped else 0


def discounted(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """The return from each step, ``sum_k gamma**k r[t + k]``, to the end of ``rewards``."""
    out, g = np.zeros(len(rewards)), 0.0
    for t in range(len(rewards) - 1, -1, -1):
        g = rewards[t] + gamma * g
        out[t] = g
    return out


class SkrlModel:
    """A benchmarks.algorithms skrl cell's saved PPO agent behind what :func:`play` asks of an SB3 model: its
    deterministic action (``predict``), its critic's ``V(s)`` (``value``), ``gamma`` and ``num_timesteps``."""

    def __init__(self, cell: str, path: Path):
        from benchmarks.algorithms import load_skrl_cell, read_state

        self.agent, self.space, tuned = load_skrl_cell(cell, path, backend="cpu")
        self.gamma = float((tuned or {}).get("agent", {}).get("discount_factor", 0.99))  # skrl PPO_CFG's default
        best = path.parent / "best.json"  # a selected agent: the env steps it was selected at
        steps = json.loads(best.read_text())["best"]["env_steps"] if best.is_file() else None
        self.num_timesteps = int(read_state(path.parent)["env_steps"] if steps is None else steps)

    def predict(self, x, deterministic: bool = True) -> tuple[np.ndarray, None]:
        from maniskill_irb120.integrations.skrl import deterministic_action

        return deterministic_action(self.agent, self.space, x).cpu().numpy(), None

    def value(self, obs_t) -> tuple[float, float]:
        from maniskill_irb120.integrations.skrl import deterministic_value

        return float(deterministic_value(self.agent, self.space, obs_t)[0]), float("nan")


def value_of(model, obs_t) -> tuple[float, float]:
    """The learner's own estimate from ``obs_t``: min of the twin ``Q(s, pi(s))`` (PPO: ``V(s)``), and the same
    critic's value of holding the arm still (arm components 0, the gripper as ``pi``'s; nan for PPO)."""
    import torch

    if isinstance(model, SkrlModel):
        return model.value(obs_t)
    policy = model.policy
    with torch.no_grad():
        if hasattr(policy, "critic"):
            a = policy._predict(obs_t, deterministic=True)
            still = torch.cat([torch.zeros_like(a[:, :-1]), a[:, -1:]], dim=1)
            q = [float(torch.cat(policy.critic(obs_t, x), dim=1).min()) for x in (a, still)]
            return q[0], q[1]
        return float(policy.predict_values(obs_t).reshape(-1)[0]), float("nan")


def tool_position(env) -> torch.Tensor:
    """The TCP's position, (3,), of one env (``tcp_pose`` is a tensor or ManiSkill's Pose)."""
    pose = env.unwrapped.tcp_pose
    return getattr(pose, "raw_pose", pose)[0, :3].clone()


def play(args: Args, model, norm, gamma: float) -> list[dict]:
    """The episodes, step by step: stage, action, tool speed, value, reward."""
    import gymnasium as gym
    import torch

    import maniskill_irb120  # noqa: F401

    env = gym.make(args.env_id, obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    bonus = gamma / (1 - gamma) if args.absorbing_bonus else 0.0
    dt = 1.0 / env.unwrapped.control_freq
    limit = args.max_steps or env.spec.max_episode_steps or 10**6
    episodes = []
    try:
        for seed in range(args.first_seed, args.first_seed + args.episodes):
            o, info = env.reset(seed=seed)
            noise = np.random.default_rng(seed)
            if args.stochastic:  # the sampled policy's draws, the same for an episode's seed in every run
                torch.manual_seed(seed)
            stage, tcp = 0, tool_position(env)
            rows: dict[str, list] = {
                k: [] for k in ("stage", "reached", "action", "tool_speed", "value", "q_still", "reward")
            }
            rows.update({k: [] for k in EXTRA})
            end = "truncated"
            for _ in range(limit):
                x = o.numpy() if norm is None else norm.normalize_obs(o.numpy())
                obs_t = torch.as_tensor(x, dtype=torch.float32)
                q, q_still = value_of(model, obs_t)
                rows["value"].append(q)
                rows["q_still"].append(q_still)
                a = model.predict(x, deterministic=not args.stochastic)[0]
                if args.action_noise > 0:
                    a = np.clip(a + noise.normal(0.0, args.action_noise, np.shape(a)), -1.0, 1.0).astype(np.float32)
                o, r, term, trunc, info = env.step(torch.as_tensor(a))
                now = tool_position(env)
                reward = float(r[0])
                if bool(term[0]) and bool(info["success"][0]):
                    reward += bonus
                rows["stage"].append(stage)
                rows["action"].append(np.asarray(a).reshape(-1).tolist())
                rows["tool_speed"].append(float((now - tcp).norm()) / dt)
                rows["reward"].append(reward)
                for k in EXTRA:
                    v = info.get(k)
                    rows[k].append(float("nan") if v is None else float(np.asarray(v).reshape(-1)[0]))
                stage, tcp = step_stage(info), now
                rows["reached"].append(stage)
                if bool(term[0]) or bool(trunc[0]):
                    end = "terminated" if bool(term[0]) else "truncated"
                    break
            episodes.append(dict(seed=seed, end=end, success=bool(info["success"][0]), **rows))
    finally:
        env.close()
    return episodes


def summarise(episodes: list[dict], gamma: float, saturated: float = SATURATED) -> dict:
    """The per-stage table and the whole episodes' numbers (see the module docstring)."""
    horizon = math.ceil(math.log(0.01) / math.log(gamma)) if gamma > 0 else 1
    stages = []
    per_step: dict[str, list] = {
        k: [] for k in ("stage", "action", "arm_sat", "grip_sat", "closed", "speed", "q", "g", "still_gain", *EXTRA)
    }
    first_steps: dict[int, list[int]] = {k: [] for k in range(len(STAGES))}
    for ep in episodes:
        a = np.asarray(ep["action"], dtype=float)
        n = len(a)
        g = discounted(np.asarray(ep["reward"]), gamma)
        usable = np.ones(n, bool)
        if ep["end"] == "truncated":
            usable[max(0, n - horizon) :] = False
        reached = np.asarray(ep["reached"])
        for k in range(1, len(STAGES)):
            hit = np.flatnonzero(reached >= k)
            if len(hit):
                first_steps[k].append(int(hit[0]) + 1)
        per_step["stage"].append(np.asarray(ep["stage"]))
        per_step["action"].append(a)
        for k in EXTRA:
            per_step[k].append(np.asarray(ep[k], dtype=float))
        per_step["arm_sat"].append(np.abs(a[:, :-1]) > saturated)
        per_step["grip_sat"].append(np.abs(a[:, -1]) > saturated)
        per_step["closed"].append(a[:, -1] <= 0)
        per_step["speed"].append(np.asarray(ep["tool_speed"]))
        per_step["q"].append(np.where(usable, ep["value"], np.nan))
        per_step["g"].append(np.where(usable, g, np.nan))
        per_step["still_gain"].append(np.asarray(ep["q_still"]) - np.asarray(ep["value"]))
    cat = {k: np.concatenate(v) for k, v in per_step.items()}

    def mean(x) -> Optional[float]:
        x = np.asarray(x, dtype=float)
        x = x[~np.isnan(x)]
        return float(x.mean()) if x.size else None

    for k, name in enumerate(STAGES):
        sel = cat["stage"] == k
        q, g = cat["q"][sel], cat["g"][sel]
        stages.append(
            dict(
                stage=name,
                episodes_reaching=1.0 if k == 0 else len(first_steps[k]) / len(episodes),
                first_step=1.0 if k == 0 else mean(first_steps[k]),
                steps=int(sel.sum()),
                arm_saturated=mean(cat["arm_sat"][sel].reshape(-1)),
                gripper_saturated=mean(cat["grip_sat"][sel]),
                gripper_closed=mean(cat["closed"][sel]),
                tool_speed=mean(cat["speed"][sel]),
                q=mean(q),
                realised_return=mean(g),
                q_minus_return=mean(q - g),
                q_still_minus_q=mean(cat["still_gain"][sel]),
                mean_action=cat["action"][sel].mean(axis=0).tolist() if sel.any() else None,
                **{k: mean(cat[k][sel]) for k in EXTRA},
            )
        )
    tail = [np.asarray(ep["tool_speed"][-20:]) for ep in episodes]
    tail_sat = [np.abs(np.asarray(ep["action"])[-20:, :-1]) > saturated for ep in episodes]
    switches = [int(np.sum(np.diff(np.asarray(ep["action"])[:, -1] <= 0) != 0)) for ep in episodes]
    return dict(
        episodes=len(episodes),
        success_rate=float(np.mean([ep["success"] for ep in episodes])),
        episode_len=float(np.mean([len(ep["reward"]) for ep in episodes])),
        gamma=gamma,
        horizon=horizon,
        stages=stages,
        last_20_steps=dict(
            tool_speed=float(np.mean(np.concatenate(tail))),
            arm_saturated=float(np.mean(np.concatenate([t.reshape(-1) for t in tail_sat]))),
        ),
        gripper_switches=float(np.mean(switches)),
        q_minus_return=mean(cat["q"] - cat["g"]),
    )


def replay_summary(path: Path) -> dict:
    """What a saved replay buffer holds: transitions by reward stage, the lifted ones as still as a hold, the arm's
    actions there, and those with the absorbing bonus (successes). Stages by ``normalized_dense``'s bands."""
    from stable_baselines3.common.save_util import load_from_pkl

    from maniskill_irb120.envs.grasp_lift import SETTLE_SPEED, STILL_SPEED

    buf = load_from_pkl(path)
    n = buf.buffer_size if buf.full else buf.pos
    r = np.asarray(buf.rewards[:n], dtype=float).reshape(-1)
    arm = np.abs(np.asarray(buf.actions[:n], dtype=float).reshape(r.size, -1)[:, :-1])
    dones = np.asarray(buf.dones[:n]).reshape(-1).astype(bool)
    timeouts = np.asarray(getattr(buf, "timeouts", np.zeros_like(buf.dones))[:n]).reshape(-1).astype(bool)
    band = np.floor(np.clip(r, 0, 1) * 4 + 1e-9).astype(int)
    lifted = band == 2
    still = 0.5 + (1 - math.tanh(STILL_SPEED / SETTLE_SPEED)) / 8  # GraspLift: lifted and settled to 2 cm/s
    return dict(
        transitions=int(r.size),
        by_stage=dict(
            reach=int(np.sum(band == 0)),
            grasped=int(np.sum(band == 1)),
            lifted=int(lifted.sum()),
            success=int(np.sum(r >= 1.0)),
        ),  # fmt: skip
        lifted_still=int(np.sum(lifted & (r >= still - 1e-6))),
        lifted_arm_saturated=float((arm[lifted] > SATURATED).mean()) if lifted.any() else None,
        lifted_arm_near_zero=float((arm[lifted] < 0.1).all(axis=1).mean()) if lifted.any() else None,
        bonus=int(np.sum(r > 1.0 + 1e-6)),
        terminations=int(np.sum(dones & ~timeouts)),
        reward_max=float(r.max()) if r.size else None,
    )


def table(summary: dict, label: str = "") -> str:
    def f(x, spec=".2f") -> str:
        return "-" if x is None else format(x, spec)

    head = f"{label} success {summary['success_rate']:.2f}, {summary['episodes']} episodes, mean length "
    head += f"{summary['episode_len']:.1f}, gamma {summary['gamma']}"
    cols = "stage     reached  first  steps  arm|a|>.99  grip|a|>.99  closed  tool m/s  Q(s,pi)  return  Q-return"
    cols += "  ik_unreach  obj m/s  Q(still)-Q"
    lines = [head, cols]
    for s in summary["stages"]:
        lines.append(
            f"{s['stage']:<9} {f(s['episodes_reaching']):>7}  {f(s['first_step'], '.1f'):>5}  {s['steps']:>5}  "
            f"{f(s['arm_saturated']):>10}  {f(s['gripper_saturated']):>11}  {f(s['gripper_closed']):>6}  "
            f"{f(s['tool_speed'], '.3f'):>8}  {f(s['q']):>7}  {f(s['realised_return']):>6}  {f(s['q_minus_return']):>8}"
            f"  {f(s['ik_unreachable']):>10}  {f(s['object_speed'], '.3f'):>7}  {f(s['q_still_minus_q']):>10}"
        )
    t = summary["last_20_steps"]
    lines.append(
        f"last 20 steps: tool {t['tool_speed']:.3f} m/s, arm saturated {t['arm_saturated']:.2f}; gripper switches "
        f"per episode {summary['gripper_switches']:.1f}; Q - return overall {f(summary['q_minus_return'])}"
    )
    return "\n".join(lines)


def main(args: Args) -> dict:
    import torch

    from agents.configs import loader

    torch.set_num_threads(1)
    if args.skrl_cell is not None:
        algo, model = f"skrl {args.skrl_cell}", SkrlModel(args.skrl_cell, Path(args.model))
    else:
        algo = args.algo or model_algo(args.model)
        model = loader.sb3_class(algo).load(args.model, device="cpu")
    norm = pickle.loads(Path(args.vecnormalize).read_bytes()) if args.vecnormalize else None
    gamma = float(model.gamma if args.gamma is None else args.gamma)
    episodes = play(args, model, norm, gamma)
    summary = summarise(episodes, gamma)
    out = dict(model=str(args.model), algo=algo, env_id=args.env_id, first_seed=args.first_seed,
               absorbing_bonus=args.absorbing_bonus, action_noise=args.action_noise, stochastic=args.stochastic,
               env_steps=int(model.num_timesteps), **summary)  # fmt: skip
    if args.replay is not None:
        out["replay"] = replay_summary(args.replay)
    out["per_episode"] = [
        dict(
            seed=ep["seed"],
            end=ep["end"],
            success=ep["success"],
            length=len(ep["reward"]),
            first_step={
                name: next((t + 1 for t, s in enumerate(ep["reached"]) if s >= k), None)
                for k, name in enumerate(STAGES)
                if k
            },
        )  # fmt: skip
        for ep in episodes
    ]
    explore = f" (action noise σ {args.action_noise:g})" if args.action_noise > 0 else " (sampled)" * args.stochastic
    print(table(out, f"{algo} {args.model}{explore}:"))
    if "replay" in out:
        print("replay:", json.dumps(out["replay"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    return out


def cli(argv: Optional[list[str]] = None) -> object:
    """The command line (``argv``, default ``sys.argv[1:]``): bad input is one line and exit status 2."""
    from benchmarks.lib.cli import entry

    return entry("scripts.diagnose_policy", Args, main, check, argv=argv)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    cli()
