"""SAC with demonstrations in the RLPD style (Ball et al. 2023), from state or from the RGB-D camera: expert demos
in a buffer every minibatch draws ``--demo-ratio`` from, LayerNorm critics, an actor cloned from DART-noise demos and
kept near a frozen reference (IBRL, arXiv 2311.02198), a delivery absorbing at the maximum reward. This file is
SAC's part only (:class:`SACRun`); the run around it is agents.common.loop's. See docs/training.md.

    python -m agents.sac --recipe sac-state --total-env-steps 49726
    python -m agents.sac --resume runs/NAME/checkpoints/latest.pt
    python -m agents.sac --obs state --evaluate --checkpoint runs/NAME/checkpoints/latest.pt
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn.functional as F
from mani_skill.utils.registration import REGISTERED_ENVS

import maniskill_irb120  # noqa: F401  (registers the envs)
from agents.common import (
    EVAL_SEED,
    Clock,
    Dataset,
    EpisodeTracker,
    RunArgs,
    atomic_save,
    check_budget,
    check_resume_signature,
    checkpoint,
    entry,
    evaluate_checkpoint,
    flatten_obs,
    held_out_evaluation,
    labelled_envs,
    load_for_evaluation,
    load_torch,
    loop,
    obs_to,
    phase_bar,
    prune_row_files,
    resolve_device,
    restore_dataset,
    shapes_of,
    train_seed,
)
from agents.common.loop import Algorithm
from maniskill_irb120.policies import policy_module, policy_section, section_of
from maniskill_irb120.policies.nets import random_shift
from maniskill_irb120.policies.sac import SAC

FORMAT = "maniskill_irb120.sac/1"


@dataclass
class Args(RunArgs):
    obs: Literal["state", "rgbd"] = "state"
    """state: privileged state vector; rgbd: 84x84 RGB-D hand camera + proprioception"""
    action_frame: Literal["world", "tool"] = "world"
    """world: translation in world axes (WorldFrameToolAction); tool: the raw tool-frame action"""
    obs_without: tuple[str, ...] = ()
    """observation keys the policy does not see, e.g. agent/qvel (DropObservationKeys)"""
    num_envs: int = 2
    """CPU envs (env 0 here, the others in worker processes), or the size of one GPU-batched env (--backend gpu)"""
    demo_episodes: int = 50
    """reactive-expert episodes in the demo buffer (0: plain SAC)"""
    dart_noise: float = 0.2
    """std of the Gaussian on the demo episodes' executed arm actions (DART); the cloning learns the clean labels"""
    demo_ratio: float = 0.5
    """fraction of every minibatch drawn from the demo buffer (RLPD's symmetric sampling)"""
    bc_pretrain_updates: int = 2000
    """actor behaviour-cloning updates on the demos before RL"""
    critic_warmup_updates: int = 2000
    """critic-only updates on the demos (actor fixed) before RL"""
    bc_weight: float = 1.0
    """weight of the MSE-to-demo-action term in the actor loss, on the demo half of each batch"""
    init_std: float = 0.1
    """the std (before the tanh) the cloning also fits the policy to, and the clone's exploration noise"""
    updates_per_step: float = 0.5
    """gradient updates per environment transition (update-to-data ratio)"""
    learning_starts: int = 1000
    """online transitions before updates begin (without demos; with them updates begin at once)"""
    reference: bool = True
    """IBRL: keep the clone frozen and act and bootstrap with the better of its and the actor's action"""
    reference_weight: float = 1.0
    """weight of the MSE from the actor's action to the frozen clone's, on every state of the batch"""
    actor_delay: int = 5000
    """online transitions during which only the critic learns, on the cloned policy's own rollouts"""
    buffer_size: Optional[int] = None
    """online transitions kept, oldest dropped first (default 300,000 from state, 50,000 from rgbd)"""
    batch_size: int = 256
    """minibatch size, demos and online data together"""
    gamma: float = 0.95
    """discount for the ~75-step episodes"""
    tau: float = 0.005
    """Polyak rate of the target critic"""
    policy_lr: float = 1e-4
    """Adam learning rate of the actor (and of the cloning before RL)"""
    q_lr: float = 3e-4
    """Adam learning rate of the critics and of the entropy temperature"""
    init_alpha: float = 0.001
    """initial entropy temperature (tuned towards entropy -|A| from there)"""
    eval_deterministic: bool = True
    """evaluate the mean action (with a reference: the better of it and the clone's), else as in training"""
    reward_mode: str = "normalized_dense"
    """the task reward SAC maximises (normalized_dense: staged, in [0, 1] per step)"""
    augment: bool = True
    """rgbd: DrQ random shifts of the images in every update"""
    log_freq: int = 1000
    """env steps between TensorBoard points"""
    save_freq: int = 20_000
    """env steps between checkpoints; always at the end (both buffers beside it, each save writing only the
    rows new since the last)"""


ROW_FIELDS = ("rew", "term", "succ", "label")


make_envs = labelled_envs
"""this run's envs, each state labelled (agents.common.envs.labelled_envs)"""


def split(batch: dict) -> tuple[dict, torch.Tensor, torch.Tensor, dict, torch.Tensor]:
    """A replay sample stored as one dict: (obs, reward, terminated, next obs) and the action."""
    obs = {k: v for k, v in batch.items() if not k.startswith("next_") and k not in ROW_FIELDS}
    nxt = {k[5:]: v for k, v in batch.items() if k.startswith("next_")}
    return obs, batch["rew"], batch["term"], nxt


def sample(online: Dataset, demos: Dataset, args: Args, device) -> tuple[dict, torch.Tensor, int]:
    """A minibatch with ``demo_ratio`` of it from the demos (first ``n_demo`` rows)."""
    n_demo = int(round(args.batch_size * args.demo_ratio)) if demos.size else 0
    if online.size == 0:
        n_demo = args.batch_size
    parts = []
    if n_demo:
        parts.append(demos.sample(n_demo, device))
    if args.batch_size - n_demo:
        parts.append(online.sample(args.batch_size - n_demo, device))
    label = parts[0][0].pop("label", parts[0][1])[:n_demo] if n_demo else None
    obs = {k: torch.cat([p[0][k] for p in parts]) for k in parts[-1][0] if k != "label"}
    act = torch.cat([p[1] for p in parts])
    if label is not None:  # the expert's clean action on the demo rows (the BC term's target)
        obs["label"] = torch.cat([label, act[n_demo:]])
    if args.obs == "rgbd" and args.augment:
        obs = random_shift(obs)
        nxt = random_shift({k[5:]: v for k, v in obs.items() if k.startswith("next_")})
        obs.update({f"next_{k}": v for k, v in nxt.items()})
    return obs, act, n_demo


def update(model: SAC, opts: dict, batch: dict, act: torch.Tensor, n_demo: int, args: Args, actor: bool) -> dict:
    obs, rew, term, nxt = split(batch)
    alpha = model.log_alpha.exp().detach()
    with torch.no_grad():
        nf = model.critic.features(nxt)
        na, nlogp, _ = model.actor(nf)
        tf = model.target.features(nxt)
        next_v = torch.min(*model.target(tf, na)) - alpha * nlogp
        if model.reference is not None:  # IBRL: bootstrap from the better of the actor's and the clone's action
            next_v = torch.max(next_v, torch.min(*model.target(tf, model.reference(nxt))))
        target = rew + args.gamma * (1 - term) * next_v
        if "succ" in batch:  # success is absorbing at the maximum reward (see transitions)
            target = torch.where(batch["succ"] > 0, rew / (1 - args.gamma), target)
    feats = model.critic.features(obs)
    q1, q2 = model.critic(feats, act)
    q_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
    opts["q"].zero_grad()
    q_loss.backward()
    opts["q"].step()
    with torch.no_grad():
        for p, tp in zip(model.critic.parameters(), model.target.parameters()):
            tp.lerp_(p, args.tau)
    out = dict(q_loss=q_loss.item(), q=q1.mean().item())
    if not actor:
        return out
    f = feats.detach()
    a, logp, mean = model.actor(f)
    qa1, qa2 = model.critic(f, a)
    pi_loss = (alpha * logp - torch.min(qa1, qa2)).mean()
    # scaled by |Q| so the cloning terms keep their weight as the Q-values grow (TD3+BC's normalisation)
    scale = torch.min(qa1, qa2).abs().mean().detach().clamp(min=1.0)
    if n_demo and args.bc_weight > 0:
        target = batch.get("label", act)[:n_demo]
        pi_loss = pi_loss + args.bc_weight * scale * F.mse_loss(mean[:n_demo], target)
    if model.reference is not None and args.reference_weight > 0:  # stay near the clone on every state
        with torch.no_grad():
            clone = model.reference(obs)
        pi_loss = pi_loss + args.reference_weight * scale * F.mse_loss(mean, clone)
    opts["pi"].zero_grad()
    pi_loss.backward()
    opts["pi"].step()
    alpha_loss = -(model.log_alpha * (logp.detach() - model.action_dim).mean()).mean()  # target entropy -|A|
    opts["alpha"].zero_grad()
    alpha_loss.backward()
    opts["alpha"].step()
    out.update(pi_loss=pi_loss.item(), alpha=alpha.item(), entropy=-logp.mean().item())
    return out


def transitions(obs: dict, action, reward, term, o, info) -> tuple[dict, torch.Tensor]:
    """The replay rows of one vector step (the real next observation where an episode ended).

    ``succ`` marks a step that ended its episode in success. Its target is the absorbing return of the
    success reward, ``r / (1 - gamma)``: cut off at the terminal step, success would be worth 1.0 once while
    holding the cube (0.75 a step) is worth ~15, and SAC learns to grasp and hold rather than deliver.
    Failures (a collision) stay terminal with no future, as in agents.ppo's ``bootstrap_mask``."""
    nxt = flatten_obs(o)
    succ = torch.zeros(len(reward), dtype=torch.bool)
    if "final_observation" in info:
        done = info["_final_observation"] if "_final_observation" in info else torch.ones(len(reward), dtype=bool)
        fin = flatten_obs(info["final_observation"])
        nxt = {k: torch.where(done.view(-1, *[1] * (v.dim() - 1)), fin[k], v) for k, v in nxt.items()}
        final = info.get("final_info", {})
        if "success" in final:
            succ = final["success"].bool().cpu() & done.bool().cpu() & term.bool().cpu()
    row = dict(obs, rew=reward.float(), term=term.float(), succ=succ.float())
    row.update({f"next_{k}": v for k, v in nxt.items()})
    return row, action


def bc_step(model: SAC, opt, demos: Dataset, args: Args, device) -> float:
    """One behaviour-cloning update of the actor (and the shared encoder) on a demo minibatch."""
    batch, act = demos.sample(args.batch_size, device)
    act = batch.get("label", act)
    obs, *_ = split(batch)
    if args.obs == "rgbd" and args.augment:
        obs = random_shift(obs)
    mean, log_std = model.actor.gaussian(model.critic.features(obs))
    loss = F.mse_loss(torch.tanh(mean), act)
    loss = loss + F.mse_loss(log_std, torch.full_like(log_std, float(np.log(args.init_std))))
    opt.zero_grad()
    loss.backward()
    opt.step()
    return loss.item()


def pretrain(model: SAC, opts: dict, online: Dataset, demos: Dataset, args: Args, device, bar=None) -> float:
    """Clone the actor from the demos, then warm the critic up on them; the cloning continues through the
    warm-up, since the critic's updates move the encoder the actor reads. ``bar``: ticked once per update."""
    bc_opt = torch.optim.Adam(list(model.actor.parameters()) + list(model.critic.encoder.parameters()), args.policy_lr)
    loss = float("nan")
    for _ in range(args.bc_pretrain_updates):
        loss = bc_step(model, bc_opt, demos, args, device)
        bar is not None and bar.update(1)
    for _ in range(args.critic_warmup_updates):
        batch, act, _ = sample(online, demos, args, device)
        update(model, opts, batch, act, 0, args, actor=False)
        if args.bc_pretrain_updates:
            loss = bc_step(model, bc_opt, demos, args, device)
        bar is not None and bar.update(1)
    return loss


def save(path: Path, model: SAC, opts: dict, online: Dataset, demos: Dataset, counters: dict, args: Args, rows=None):
    """The checkpoint, with the replay and the demos beside it in ``data/online`` and ``data/demos``, each save
    writing only the rows new since the last (``rows``: the last save's manifests): returns the new manifests."""
    data = dict(online=online, demos=demos)
    rows = {k: d.save_new_rows(path.parent / "data" / k, (rows or {}).get(k)) for k, d in data.items()}
    opts = {k: o.state_dict() for k, o in opts.items()}
    save_policy(path, model, counters, args, opts=opts, data_rows=rows)
    for k, manifest in rows.items():
        prune_row_files(path.parent / "data" / k, manifest)
    return rows


def save_policy(path: Path, model: SAC, counters: dict, args: Args, **state) -> None:
    """A checkpoint of ``model`` and its policy section, with ``state`` beside it (none: ``best.pt``, a policy to
    deploy, not a run to continue)."""
    atomic_save(
        checkpoint(
            FORMAT,
            args,
            counters,
            model=model.state_dict(),
            signature=model.signature(),
            **state,
            policy=policy_section(
                "sac",
                model,
                dict(model.signature(), init_alpha=1.0),  # log_alpha comes with the weights
                env_id=args.env_id,
                obs=args.obs,
                action_frame=args.action_frame,
                obs_without=args.obs_without,
                reward_mode=args.reward_mode,
                env_kwargs=args.env_kwargs,
                eval_deterministic=args.eval_deterministic,
                init_std=args.init_std,
            ),
        ),
        path,
    )


def load_model(path: Path, device) -> tuple[SAC, dict]:
    ckpt = load_for_evaluation(path, FORMAT, "agents.sac", "sac")
    return policy_module(section_of(ckpt, str(path)), device), ckpt


def final_evaluation(model: SAC, args: Args, device, video_dir: Optional[Path], first_seed: int = EVAL_SEED) -> dict:
    torch.manual_seed(first_seed)  # a stochastic evaluation's noise is seeded too
    return held_out_evaluation(
        lambda o: model.act(obs_to(o, device), deterministic=args.eval_deterministic, noise=args.init_std).cpu(),
        args,
        video_dir,
        first_seed,
        reward_mode=args.reward_mode,
    )


def run_evaluation_only(args: Args) -> dict:
    device = resolve_device(args.device)
    return evaluate_checkpoint(
        args,
        lambda path: load_model(path, device),
        lambda policy, videos: final_evaluation(policy, args, device, videos),
    )


def collect_demos(envs, state: dict, demos: Dataset, episodes: int, noise: float = 0.0, bar=None) -> int:
    """Reactive-expert episodes into ``demos``, with DART noise on the executed arm actions: each row keeps the
    executed action (the critic's) and the expert's clean ``label`` (the cloning's), so the clone also learns to
    recover from the states noise leads to. Returns the env steps taken (``bar``: ticked per finished episode)."""
    finished = steps = 0
    while finished < episodes:
        label = state["label"]
        action = label.clone()
        action[:, :4] += noise * torch.randn(len(action), 4)
        action = action.clamp(-1, 1)
        o, rew, term, trunc, info = envs.step(action)
        row, act = transitions(state["obs"], action, rew, term, o, info)
        row["label"] = label
        demos.add(row, act)
        state["obs"], state["label"] = flatten_obs(o), info["expert_action"].float()
        done = int((term | trunc).sum())
        finished += done
        steps += envs.num_envs
        bar is not None and done and bar.update(done)
    return steps


def online_rows(args: Args) -> int:
    """--buffer-size, or its default for the observation (a camera row is ~70 kB: 300k of them are 21 GB)."""
    if args.buffer_size is None:
        return 50_000 if args.obs == "rgbd" else 300_000
    if args.buffer_size < 1:
        raise ValueError(f"--buffer-size {args.buffer_size}: keep at least one transition")
    return args.buffer_size


def resolved(args: Args) -> Args:
    """The arguments as a run logs them: the defaults that depend on other flags filled in (benchmarks/learning.py
    checks an adopted run's log against its recipe through this)."""
    return replace(args, buffer_size=online_rows(args))


def demo_rows(args: Args) -> int:
    """Every demo step: the envs still mid-episode when the last demo ends keep adding theirs."""
    return max(1, (args.demo_episodes + args.num_envs) * REGISTERED_ENVS[args.env_id].max_episode_steps)


class SACRun(Algorithm):
    """SAC's part of a run (agents.common.loop): the demos and the cloning before the first step (:meth:`start`),
    then a step is one vector env step and the updates it pays for (``--updates-per-step``)."""

    name, prefix, default_minutes = "sac", "sac__", 120.0

    def __init__(self, args: Args):
        super().__init__(resolved(args))
        self.counters = dict(env_steps=0, updates=0, episodes=0, wall_s=0.0, pretrained=False)
        self.device = resolve_device(args.device)
        self.rows = None  # the manifests of the datasets' row files on disk
        self.recent: dict[str, list[float]] = {}
        self.losses: dict[str, float] = {}
        self.owed = 0.0

    def read(self, path: Path) -> dict:
        return load_torch(path, FORMAT, "agents.sac")

    def build(self, saved: Optional[dict]):
        args = self.args
        self.envs = make_envs(args, args.num_envs)
        image_shape, state_dim = shapes_of(self.envs.single_observation_space)
        reference = saved is not None and saved["signature"].get("reference", False)
        action_dim = int(np.prod(self.envs.single_action_space.shape))
        self.model = model = SAC(image_shape, state_dim, action_dim, args.init_alpha, reference).to(self.device)
        self.opts = dict(
            q=torch.optim.Adam(model.critic.parameters(), lr=args.q_lr),
            pi=torch.optim.Adam(model.actor.parameters(), lr=args.policy_lr),
            alpha=torch.optim.Adam([model.log_alpha], lr=args.q_lr),
        )
        self.online, self.demos = Dataset(args.buffer_size), Dataset(demo_rows(args))
        if saved is not None:
            check_resume_signature(saved, model.signature(), args.resume, args)
            model.load_state_dict(saved["model"])
            for k, o in self.opts.items():
                o.load_state_dict(saved["opts"][k])
            self.rows = saved.get("data_rows")
            restore_dataset(self.online, saved, Path(args.resume).parent / "data", "online")
            restore_dataset(self.demos, saved, Path(args.resume).parent / "data", "demos")
        return self.envs

    def start(self) -> None:
        args, model, counters = self.args, self.model, self.counters
        self.next_save = counters["env_steps"] + args.save_freq
        self.next_log = counters["env_steps"] + args.log_freq
        o, info = self.envs.reset(seed=train_seed(args.seed, counters["episodes"]))
        self.state = dict(obs=flatten_obs(o), label=info["expert_action"].float())
        self.tracker = EpisodeTracker(self.envs.num_envs, torch.device("cpu"))
        if counters["pretrained"]:
            return
        if args.demo_episodes > 0:
            # minutes before the first RL step: each phase shows its own bar
            with phase_bar(args, args.demo_episodes, "expert demos", "episode") as bar:
                steps = collect_demos(self.envs, self.state, self.demos, args.demo_episodes, args.dart_noise, bar)
            counters["env_steps"] += steps
            model.critic.norm.fit(self.demos.obs["state"][: self.demos.size])
            model.target.norm.load_state_dict(model.critic.norm.state_dict())
            updates = args.bc_pretrain_updates + args.critic_warmup_updates
            with phase_bar(args, updates, "cloning + critic warm-up", "update") as bar:
                bc = pretrain(model, self.opts, self.online, self.demos, args, self.device, bar)
            self.logger.scalars({"losses/bc_pretrain": bc}, counters["env_steps"])
            if args.reference:
                model.freeze_reference()
        counters["pretrained"] = True

    def step(self, budget) -> dict:
        args, model, counters, envs = self.args, self.model, self.counters, self.envs
        online, demos, obs = self.online, self.demos, self.state["obs"]
        if online.size < args.learning_starts and demos.size == 0:
            action = torch.rand(envs.num_envs, model.action_dim) * 2 - 1
        else:
            action = model.act(obs_to(obs, self.device), deterministic=False, noise=args.init_std).cpu()
        o, rew, term, trunc, info = envs.step(action)
        row, act = transitions(obs, action, rew, term, o, info)
        online.add(row, act)
        self.state["obs"], self.state["label"] = flatten_obs(o), info["expert_action"].float()
        done = (term | trunc).bool()
        counters["env_steps"] += envs.num_envs
        counters["episodes"] += int(done.sum())
        for k, v in self.tracker.update(info.get("final_info", info), done).items():
            self.recent.setdefault(k, []).extend(v)
        if not demos.size and not counters.get("norm_fitted") and online.size >= args.learning_starts:
            # without demos the state normaliser is fitted on the random-action steps before learning starts:
            # identity scales would hide the grasp's millimetres next to the joints' radians
            model.critic.norm.fit(online.obs["state"][: online.size])
            model.target.norm.load_state_dict(model.critic.norm.state_dict())
            counters["norm_fitted"] = True
        if online.size >= args.learning_starts or demos.size:
            self.owed += args.updates_per_step * envs.num_envs
            while self.owed >= 1:
                batch, act, n_demo = sample(online, demos, args, self.device)
                actor = online.size >= args.actor_delay or not demos.size
                self.losses = update(model, self.opts, batch, act, n_demo, args, actor=actor)
                counters["updates"] += 1
                self.owed -= 1
        if counters["env_steps"] < self.next_log:
            return {}
        self.next_log += args.log_freq
        scalars = {f"train/{k}": float(np.mean(v)) for k, v in self.recent.items()}
        scalars.update({f"losses/{k}": v for k, v in self.losses.items()})
        scalars["charts/updates"] = counters["updates"]
        self.recent = {}
        return scalars

    def postfix(self, scalars: dict) -> dict:
        return dict(steps=self.counters["env_steps"], success=f"{scalars.get('train/success_rate', 0):.2f}")

    def save(self, path: Path, counters: dict) -> None:
        self.rows = save(path, self.model, self.opts, self.online, self.demos, counters, self.args, self.rows)

    def save_periodic(self, ckpt_dir: Path, counters: dict, last: bool) -> None:
        if counters["env_steps"] >= self.next_save:
            self.next_save += self.args.save_freq
            self.save(ckpt_dir / "latest.pt", counters)

    def save_selected(self, path: Path, counters: dict) -> None:
        save_policy(path, self.model, counters, self.args)

    def load_selected(self, path: Path) -> None:
        self.model.load_state_dict(load_torch(path, FORMAT, "agents.sac")["model"])

    def evaluate(self, args: Args, video_dir: Optional[Path] = None, first_seed: int = EVAL_SEED) -> dict:
        training = self.model.training
        self.model.eval()
        try:
            return final_evaluation(self.model, args, self.device, video_dir, first_seed)
        finally:
            self.model.train(training)

    def summary(self) -> dict:
        return dict(updates=self.counters["updates"], train_episodes=self.counters["episodes"])


def train(args: Args) -> dict:
    return loop.run(SACRun(args), Clock)


def main(args: Args) -> dict:
    if not 0.0 <= args.demo_ratio <= 1.0:
        raise ValueError(f"--demo-ratio must be in [0, 1], got {args.demo_ratio}")
    if not args.init_std > 0:
        raise ValueError(f"--init-std must be > 0, got {args.init_std}")
    check_budget(args)
    return run_evaluation_only(args) if args.evaluate else train(args)


if __name__ == "__main__":
    entry(Args, "agents.sac", main)
