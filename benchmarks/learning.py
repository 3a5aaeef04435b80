"""Does it learn? A fixed wall-clock budget of PPO on this machine, against a random policy measured
in the same run.

Arms (state observations, CPU worker processes, ``normalized_dense`` reward):

- ``random``: uniform random actions (the floor);
- ``ppo``: PPO from scratch for half the budget;
- ``bc+ppo``: PPO for the other half, warm-started by behaviour cloning on scripted-expert
  demonstrations (the seed estimated 80M steps for PPO from scratch; a few thousand expert
  transitions put the policy where PPO's reward signal is dense enough to improve it in minutes).

Every arm ends with the same deterministic evaluation (success, grasp rate, the seed's dense return).
Writes ``--out-dir``/learning.json and learning.png (curves against wall time and env steps).

    python benchmarks/learning.py --budget-min 30          # the reported run
    python benchmarks/learning.py --budget-min 2 --eval-episodes 5   # a smoke run
"""

from __future__ import annotations

import functools
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agents.ppo import Agent, evaluate, make_envs, save_checkpoint, train  # noqa: E402
from agents.ppo import Args as PPOArgs  # noqa: E402

ENV_ID = "TableClearing-IRB120-v1"


@dataclass
class Args:
    budget_min: float = 30.0
    """total wall-clock minutes for the two PPO arms (split evenly)"""
    num_envs: int = 4
    """CPU worker processes per PPO arm"""
    bc_episodes: int = 100
    """expert episodes for the behaviour-cloning warm start"""
    bc_epochs: int = 100
    critic_warmup_iters: int = 15
    """bc+ppo: iterations fitting only the value function before the cloned policy is updated"""
    eval_episodes: int = 20
    seed: int = 0
    out_dir: Path = Path("benchmarks/results/learning")


def ppo_args(
    args: Args,
    name: str,
    minutes: float,
    checkpoint: Path | None = None,
    lr: float = 3e-4,
    critic_warmup_iters: int = 0,
) -> PPOArgs:
    return PPOArgs(
        obs="state",
        num_envs=args.num_envs,
        num_steps=100,
        num_minibatches=4,
        update_epochs=8,
        learning_rate=lr,
        total_timesteps=10**9,
        max_wall_s=60 * minutes,
        eval_freq=0,
        save_freq=20,
        critic_warmup_iters=critic_warmup_iters,
        seed=args.seed,
        exp_name=name,
        runs_dir=args.out_dir / "runs",
        checkpoint=checkpoint,
        capture_video=False,
        progress=False,
        backend="cpu",
    )


def summary_from_eval(m: dict) -> dict:
    """agents.ppo.evaluate() means -> rates, normalized return and the seed's dense return (sum of terms)."""
    return dict(
        episodes=m["episodes"],
        success_rate=m.get("success_rate_mean", 0.0),
        grasp_rate=m.get("grasped_rate_mean", 0.0),
        collision_rate=m.get("collided_rate_mean", 0.0),
        normalized_return=m.get("return_mean", 0.0),
        dense_return=sum(v for k, v in m.items() if k.startswith("return_r_")),
    )


class RandomPolicy:
    """Uniform random actions through the same evaluation loop as the trained agents."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)

    def get_action(self, obs, deterministic: bool = False) -> torch.Tensor:
        n = next(iter(obs.values())).shape[0]
        return torch.from_numpy(self.rng.uniform(-1, 1, (n, 5)).astype(np.float32))


def evaluate_policy(policy, episodes: int) -> dict:
    envs = make_envs(PPOArgs(obs="state", backend="cpu", capture_video=False), 1, evaluate=True)
    try:
        return summary_from_eval(evaluate(policy, envs, episodes, torch.device("cpu")))
    finally:
        envs.close()


def random_baseline(episodes: int, seed: int) -> dict:
    return evaluate_policy(RandomPolicy(seed), episodes)


def expert_dataset(episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, float]:
    """(obs, action) pairs from the scripted expert, in the PPO env's flattened state observation."""
    import gymnasium as gym

    import maniskill_irb120  # noqa: F401
    from maniskill_irb120.expert import TableClearingExpert

    env = gym.make(ENV_ID, obs_mode="state", reward_mode="normalized_dense", render_backend="none")
    expert = TableClearingExpert(env.unwrapped)
    obs_l, act_l, ok = [], [], 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=10_000 + seed + ep)  # seeds disjoint from evaluation's
        expert.reset()
        while True:
            a = expert.act()
            obs_l.append(obs.clone())
            act_l.append(a.clone())
            obs, _, term, trunc, info = env.step(a)
            if bool(term[0]) or bool(trunc[0]):
                ok += bool(info["success"][0])
                break
    env.close()
    return torch.cat(obs_l), torch.cat(act_l), ok / episodes


def behaviour_clone(obs: torch.Tensor, act: torch.Tensor, epochs: int, seed: int, path: Path) -> dict:
    """Fit the PPO actor's mean to the expert's actions (MSE); save as a PPO checkpoint."""
    torch.manual_seed(seed)
    agent = Agent(None, obs.shape[1], act.shape[1])
    opt = torch.optim.Adam(list(agent.encoder.parameters()) + list(agent.actor_mean.parameters()), lr=1e-3)
    n, losses = obs.shape[0], []
    for _ in range(epochs):
        perm = torch.randperm(n)
        for i in range(0, n, 256):
            idx = perm[i : i + 256]
            loss = ((agent.actor_mean(agent.encoder({"state": obs[idx]})) - act[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        losses.append(loss.item())
    with torch.no_grad():  # start PPO's exploration narrow around the cloned behaviour
        agent.actor_logstd.fill_(-1.6)
    save_checkpoint(
        path, agent, torch.optim.Adam(agent.parameters()), dict(global_step=0, iteration=0), ppo_args(Args(), "bc", 0)
    )
    return dict(transitions=n, final_mse=losses[-1], first_mse=losses[0])


def final_eval(checkpoint: Path, episodes: int) -> dict:
    from agents.ppo import load_checkpoint

    agent = Agent(None, state_dim(), 5)
    load_checkpoint(checkpoint, agent, PPOArgs(obs="state"))
    agent.eval()
    return evaluate_policy(agent, episodes)


@functools.lru_cache(maxsize=1)
def state_dim() -> int:
    import gymnasium as gym

    import maniskill_irb120  # noqa: F401

    env = gym.make(ENV_ID, obs_mode="state", render_backend="none")
    try:
        return env.observation_space.shape[-1]
    finally:
        env.close()


def curve(history: list[dict]) -> dict:
    keys = ("train/success_rate", "train/grasped_rate", "train/return")
    pts = [h for h in history if "train/return" in h]
    return dict(
        wall_s=[h["wall_s"] for h in pts],
        global_step=[h["global_step"] for h in pts],
        **{k.split("/")[1]: [h.get(k, float("nan")) for h in pts] for k in keys},
    )


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def smooth(y, k=5):
        y = np.asarray(y, dtype=float)
        return np.convolve(y, np.ones(k) / k, mode="valid") if len(y) >= k else y

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for name, arm in result["arms"].items():
        c = arm["curve"]
        if not c["wall_s"]:
            continue
        t = np.asarray(c["wall_s"]) / 60
        for ax, key in zip(axes, ("success_rate", "grasped_rate", "return")):
            y = smooth(c[key])
            ax.plot(t[len(t) - len(y) :], y, label=name)
    base = result["random"]
    for ax, key, title in zip(
        axes,
        ("success_rate", "grasp_rate", "normalized_return"),
        ("delivery success (training episodes)", "grasp rate", "normalized return per episode"),
    ):
        ax.axhline(base[key], color="k", ls="--", lw=1, label="random policy")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("wall-clock minutes (2 CPU cores)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(args: Args) -> dict:
    args.out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result: dict = dict(
        budget_min=args.budget_min,
        num_envs=args.num_envs,
        seed=args.seed,
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=" ".join(sys.argv),
        arms={},
    )
    result["random"] = random_baseline(args.eval_episodes, args.seed)
    print("random:", json.dumps(result["random"]), flush=True)

    half = args.budget_min / 2
    scratch = train(ppo_args(args, "ppo", half))
    result["arms"]["ppo"] = dict(
        curve=curve(scratch["history"]),
        global_step=scratch["global_step"],
        final=final_eval(Path(scratch["checkpoint"]), args.eval_episodes),
    )
    print("ppo:", json.dumps(result["arms"]["ppo"]["final"]), flush=True)

    t_bc = time.perf_counter()
    obs, act, expert_success = expert_dataset(args.bc_episodes, args.seed)
    bc_ckpt = args.out_dir / "bc.pt"
    bc = behaviour_clone(obs, act, args.bc_epochs, args.seed, bc_ckpt)
    bc.update(
        expert_success=expert_success, seconds=time.perf_counter() - t_bc, final=final_eval(bc_ckpt, args.eval_episodes)
    )
    result["bc"] = bc
    print("bc:", json.dumps(bc), flush=True)
    warm = train(
        ppo_args(
            args,
            "bc_ppo",
            max(0.5, half - bc["seconds"] / 60),
            checkpoint=bc_ckpt,
            lr=1e-4,
            critic_warmup_iters=args.critic_warmup_iters,
        )
    )
    result["arms"]["bc+ppo"] = dict(
        curve=curve(warm["history"]),
        global_step=warm["global_step"],
        final=final_eval(Path(warm["checkpoint"]), args.eval_episodes),
    )
    print("bc+ppo:", json.dumps(result["arms"]["bc+ppo"]["final"]), flush=True)
    result["wall_s"] = time.perf_counter() - t0
    (args.out_dir / "learning.json").write_text(json.dumps(result, indent=1))
    plot(result, args.out_dir / "learning.png")
    print(markdown(result))
    return result


def markdown(r: dict) -> str:
    rows = [
        "| policy | env steps | success | grasp rate | collision rate | normalized return | seed's dense return |",
        "|---|---|---|---|---|---|---|",
    ]

    def row(name, steps, f):
        return (
            f"| {name} | {steps} | {f['success_rate']:.2f} | {f['grasp_rate']:.2f} | {f['collision_rate']:.2f} | "
            f"{f['normalized_return']:.2f} | {f['dense_return']:.0f} |"
        )

    rows.append(row("random", "-", r["random"]))
    rows.append(row("PPO from scratch", r["arms"]["ppo"]["global_step"], r["arms"]["ppo"]["final"]))
    rows.append(row(f"BC only ({r['bc']['transitions']} expert transitions)", 0, r["bc"]["final"]))
    rows.append(row("BC + PPO", r["arms"]["bc+ppo"]["global_step"], r["arms"]["bc+ppo"]["final"]))
    return "\n".join(rows)


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
