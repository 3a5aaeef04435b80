"""PPO from pixels (or state), ManiSkill-baseline style (``ppo_rgb.py``: GAE, clipped surrogate, advantage
normalisation, the ``normalized_dense`` reward, auto-resetting envs, separate eval envs), one code path for the
GPU-batched env and the CPU process-vector env. This file is PPO's part only (:class:`PPO`: a rollout and its update);
the run around it is agents.common.loop's. ``--base-checkpoint`` learns a residual on a frozen cloned policy
(``--kl-coef`` keeps it near it). See docs/training.md.

    python -m agents.ppo --obs state --num-envs 2 --total-env-steps 20000
    python -m agents.ppo --resume runs/NAME/checkpoints/latest.pt
    python -m agents.ppo --evaluate --eval-episodes 10 --checkpoint runs/NAME/checkpoints/latest.pt
"""

from __future__ import annotations

import copy
import threading
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim

import maniskill_irb120  # noqa: F401  (registers the env)
from agents.common import (
    EVAL_SEED,
    Budget,
    Clock,
    EpisodeTracker,
    RunArgs,
    atomic_save,
    check_budget,
    check_resume_signature,
    checkpoint,
    entry,
    env_step_budget,
    evaluate_checkpoint,
    flatten_obs,
    held_out_evaluation,
    load_torch,
    loop,
    obs_to,
    one_thread_beside_workers,
    resolve_device,
    resolve_precision,
    shapes_of,
    signature_mismatch,
    torch_threads,
    vec_envs,
)
from agents.common.envs import PRIVILEGED, PrivilegedStateObs
from agents.common.loop import Algorithm
from maniskill_irb120.policies import policy_module, policy_section, read_policy_section
from maniskill_irb120.policies.nets import random_shift
from maniskill_irb120.policies.ppo import Agent


@dataclass
class Args(RunArgs):
    eval_episodes: int = 0
    """after training (and for --evaluate): deterministic episodes on held-out seeds, one env (0: none after
    training)"""
    total_env_steps: Optional[int] = 100_000
    """the budget in env steps: an iteration starts only while fewer are done (counting the run's before a
    --resume)"""
    obs: Literal["rgbd", "state"] = "rgbd"
    """rgbd: 84x84 RGB-D hand camera + proprioception; state: privileged state vector"""
    control_mode: str = "pd_ee_delta_tool"
    """the env's controller"""
    action_frame: Literal["tool", "world"] = "tool"
    """tool: the original report's tool-frame action; world: translation in world axes (WorldFrameToolAction)"""
    base_checkpoint: Optional[Path] = None
    """an agents.dagger checkpoint: the policy is its frozen action plus a learned residual (zero at the start)"""
    init_policy: Optional[Path] = None
    """an agents.ppo checkpoint whose weights a new run starts from (optimiser and counters start fresh)"""
    kl_coef: float = 0.0
    """weight of KL(policy || N(base action, exp(init_logstd))) in the loss; needs --base-checkpoint"""
    init_logstd: float = -0.5
    """initial log std of the Gaussian policy (a fine-tuned policy wants little noise, e.g. -2)"""
    logstd: Literal["param", "state"] = "param"
    """param: one learned log std per action dimension (CleanRL, ManiSkill); state: a small head on the actor's
    input, so the noise can shrink where the task wants stillness (GraspLift's hold) and stay broad elsewhere"""
    state_net: Literal["shared", "mlp"] = "shared"
    """shared: the camera encoder's state MLP under both heads; mlp: ManiSkill's state PPO network (separate
    3x256 tanh actor and critic), for --obs state"""
    obs_norm: bool = False
    """standardise the state vector by running statistics kept in the policy (updated between updates)"""
    num_envs: int = 2
    """training envs: CPU envs (env 0 here, the others in worker processes), or one GPU-batched env's size"""
    num_eval_envs: int = 1
    """envs of the periodic evaluation"""
    num_steps: int = 50
    """rollout length per env per iteration"""
    learning_rate: float = 3e-4
    """Adam learning rate"""
    anneal_lr: bool = False
    """anneal the learning rate linearly to 0"""
    gamma: float = 0.8
    """discount"""
    gae_lambda: float = 0.9
    """GAE lambda"""
    num_minibatches: int = 4
    """minibatches per epoch"""
    update_epochs: int = 4
    """epochs over each rollout"""
    norm_adv: bool = True
    """normalise advantages per minibatch"""
    clip_coef: float = 0.2
    """surrogate clipping coefficient"""
    clip_vloss: bool = False
    """clip the value loss too"""
    ent_coef: float = 0.0
    """entropy bonus weight"""
    vf_coef: float = 0.5
    """value loss weight"""
    max_grad_norm: float = 0.5
    """gradient norm clip"""
    target_kl: Optional[float] = 0.2
    """stop an update's epochs once the approximate KL exceeds this"""
    reward_scale: float = 1.0
    """rewards are multiplied by this"""
    reward_mode: str = "normalized_dense"
    """the task reward PPO maximises"""
    absorbing_success: bool = False
    """bootstrap a delivered episode's end with the absorbing value reward_scale / (1 - gamma) (normalized_dense pays
    1 a step at success) instead of the critic's estimate of a state it never trains on; normalized_dense only"""
    eval_freq: int = 25
    """evaluate every N iterations (0: only at the end)"""
    eval_freq_episodes: int = 4
    """episodes of each --eval-freq evaluation"""
    eval_reconfiguration_freq: Optional[int] = None
    """rebuild the eval scene every N resets (None: never; the task samples nothing at scene load)"""
    save_freq: int = 10
    """checkpoint every N iterations (and always at the end)"""
    keep_checkpoints: int = 5
    """periodic checkpoints/ckpt_N.pt kept, the newest (0: every one); latest.pt and best.pt are never removed"""
    torch_deterministic: bool = True
    """cudnn.deterministic"""
    critic_warmup_iters: int = 0
    """iterations that update only the value function (keeps a warm-started policy while its critic learns)"""
    precision: Literal["fp32", "bf16", "auto"] = "fp32"
    """the camera encoder in the update: bf16 autocast (its convolutions about twice as fast on a CPU with native
    bf16), fp32, or auto (bf16 where native on a CPU, else fp32; agents/common/precision.py). The rollout's
    forward passes, the heads, log-probabilities, advantages, losses, weights and checkpoints stay float32"""
    augment: Literal["none", "shift"] = "none"
    """--obs rgbd: shift, DrQ's random shift (replicate-pad 4 px, a random 84x84 crop per sample, RGB and depth
    alike) of every update minibatch's images; the rollout acts on the images as they are"""
    critic_obs: Literal["same", "privileged"] = "same"
    """--obs rgbd: privileged, an asymmetric actor-critic: the value head reads the privileged state (the
    --obs state vector, recorded per step by the training envs) through its own 3x256 tanh MLP and running
    normaliser; the policy still reads the camera and proprioception alone, and acts without the privileged state"""
    encoder: Literal["nature", "keypoints"] = "nature"
    """--obs rgbd: the camera encoder, nature (NatureCNN) or keypoints (KeypointCNN: conv + spatial softmax, as
    agents.dagger's --encoder keypoints); checkpoints record it, so --resume, --evaluate and an export rebuild it"""
    overlap: bool = False
    """collect the next rollout in a thread while the update runs, so the envs render while the learner trains
    (a camera run's update is most of its time); the collector acts with the weights from before the update (one
    update behind) and stores its own log-probabilities, so PPO's ratio and clip cover the lag. CPU worker envs"""

    def check(self) -> None:
        """ValueError for flags that cannot run together (agents.common.check_budget calls it, before anything runs)."""
        if self.obs != "rgbd":
            camera_only = (
                ("augment", self.augment, "none"),
                ("critic-obs", self.critic_obs, "same"),
                ("encoder", self.encoder, "nature"),
            )
            for flag, value, default in camera_only:
                if value != default:
                    raise ValueError(
                        f"--{flag} {value} is for a camera policy (--obs rgbd); this run has --obs {self.obs}"
                    )
        if self.overlap and not self.evaluate and overlap_backend(self) == "gpu":
            raise ValueError(
                f"--overlap steps the CPU envs in a thread beside the update; --backend {self.backend} gives the "
                "GPU-batched env, which steps in the learner's own CUDA stream: use --backend cpu or drop --overlap"
            )

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches


def overlap_backend(args: Args) -> str:
    """The backend ``args.backend`` resolves to (``auto``: gpu when CUDA is available, as make_vec_env decides)."""
    return args.backend if args.backend != "auto" else ("gpu" if torch.cuda.is_available() else "cpu")


def make_envs(args: Args, num_envs: int, evaluate: bool = False, video_dir: Optional[Path] = None):
    """PPO's envs (agents.common.vec_envs) on its reward and controller, unlabelled, their tensors where the env
    keeps them. Training: auto-resetting envs beside this process's one thread. ``evaluate``: the periodic
    evaluation's, recorded to ``video_dir``."""
    env_kwargs = dict(reward_mode=args.reward_mode, **args.env_kwargs)
    setup = dict(action_frame=args.action_frame, control_mode=args.control_mode, env_kwargs=env_kwargs)
    if not evaluate:
        extra = [PrivilegedStateObs] if args.critic_obs == "privileged" else []  # the critic's, in training only
        return one_thread_beside_workers(
            vec_envs(args.env_id, args.obs, num_envs, backend=args.backend, outer_wrappers=extra, **setup)
        )
    from mani_skill.utils.wrappers.record import RecordEpisode

    if args.eval_reconfiguration_freq is not None:
        env_kwargs["reconfiguration_freq"] = args.eval_reconfiguration_freq
    backend = args.backend if args.backend != "auto" else ("gpu" if torch.cuda.is_available() else "inprocess")
    if backend == "cpu":
        backend = "inprocess"  # videos are recorded in this process: one env, episodes in sequence
        num_envs = 1
    record = []
    if video_dir is not None:
        record.append(
            lambda e: RecordEpisode(
                e,
                output_dir=str(video_dir),
                save_trajectory=False,
                max_steps_per_video=None,
                video_fps=20,
                info_on_video=False,
            )
        )
    # GPU: batched eval envs run fixed-length episodes without early-termination resets (as ManiSkill's
    # ppo_rgb.py does, which also allows --eval-reconfiguration-freq); success/grasp are counted "once".
    return vec_envs(
        args.env_id,
        args.obs,
        num_envs,
        backend=backend,
        render=video_dir is not None,
        outer_wrappers=record,
        ignore_terminations=backend == "gpu",
        **setup,
    )


def agent_for(envs, device, args: Args, residual: bool = False, privileged_dim: Optional[int] = None) -> Agent:
    """The agent for these envs; with ``args.base_checkpoint`` (a new run) its base is that DAgger policy,
    checked against the envs' observation and action frame. ``--critic-obs privileged``: its critic's input is the
    envs' ``privileged`` key, or ``privileged_dim`` wide (envs without the key: an evaluation's)."""
    image_shape, state_dim = shapes_of(envs.single_observation_space)
    if args.critic_obs == "privileged" and privileged_dim is None:
        privileged_dim = envs.single_observation_space[PRIVILEGED].shape[0]
    residual = residual or args.base_checkpoint is not None
    agent = Agent(
        image_shape,
        state_dim,
        int(np.prod(envs.single_action_space.shape)),
        residual,
        args.init_logstd,
        state_net=args.state_net,
        obs_norm=args.obs_norm,
        logstd=args.logstd,
        critic_obs=args.critic_obs,
        privileged_dim=privileged_dim or 0,
        encoder=args.encoder,
    )
    if args.base_checkpoint is not None:
        where = f"--base-checkpoint {args.base_checkpoint}"
        section = read_policy_section(args.base_checkpoint, where)
        if section["kind"] != "dagger":
            raise ValueError(f"{where}: a {section['kind']} policy; the base is a deterministic (dagger) policy")
        base = policy_module(section, "cpu")
        # the PPO agent's own; the base has its image and state
        own = ("residual", "state_net", "obs_norm", "logstd", "critic_obs", "privileged_dim")
        if base.signature() != {k: v for k, v in agent.signature().items() if k not in own}:
            raise ValueError(
                f"--base-checkpoint {args.base_checkpoint}: its policy takes {base.signature()}, these envs give "
                f"{agent.signature()} (obs={args.obs}; a base trained with --obs-without does not fit; --encoder "
                "must be the base's)"
            )
        if section["action_frame"] != args.action_frame or section["obs_without"]:
            raise ValueError(
                f"--base-checkpoint {args.base_checkpoint} acts in the {section['action_frame']!r} "
                f"frame without {section['obs_without'] or []}; this run: --action-frame {args.action_frame!r}, "
                "all observation keys"
            )
        agent.base.load_state_dict(base.state_dict())
    return agent.to(device)


# ----------------------------------------------------------------------------- PPO update
def ppo_update(
    agent: Agent, optimizer: optim.Optimizer, batch: dict, args: Args, critic_only: bool = False
) -> dict[str, float]:
    """Clipped-surrogate epochs over minibatches of one rollout; returns the last epoch's stats.
    ``critic_only``: value loss alone (the policy, its encoder included, stays as it is). ``args.precision``: the
    encoder's forward (and so its backward) under bf16 autocast, where a camera update spends its time; the
    ratio, advantages and losses are float32 (the heads read float32 features)."""
    n = batch["actions"].shape[0]
    precision = resolve_precision(args.precision, batch["actions"].device)
    mb = max(1, n // args.num_minibatches)
    clipfracs, stats = [], {}
    for _ in range(args.update_epochs):
        perm = torch.randperm(n, device=batch["actions"].device)
        approx_kl = torch.zeros(())
        for start in range(0, n, mb):
            idx = perm[start : start + mb]
            obs = {k: v[idx] for k, v in batch["obs"].items()}
            if args.augment == "shift":
                obs = random_shift(obs)
            _, logp, entropy, value, mean = agent.get_action_and_value(
                obs, batch["actions"][idx], with_mean=True, precision=precision
            )
            logratio = logp - batch["logprobs"][idx]
            ratio = logratio.exp()
            with torch.no_grad():
                old_approx_kl = (-logratio).mean()
                approx_kl = ((ratio - 1) - logratio).mean()
                clipfracs.append(((ratio - 1.0).abs() > args.clip_coef).float().mean().item())
            adv = batch["advantages"][idx]
            if args.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
            value = value.view(-1)
            if args.clip_vloss:
                v_clipped = batch["values"][idx] + (value - batch["values"][idx]).clamp(-args.clip_coef, args.clip_coef)
                v_loss = (
                    0.5
                    * torch.max((value - batch["returns"][idx]) ** 2, (v_clipped - batch["returns"][idx]) ** 2).mean()
                )
            else:
                v_loss = 0.5 * ((value - batch["returns"][idx]) ** 2).mean()
            ent = entropy.mean()
            if critic_only:
                x = None if agent.critic_norm is not None else agent.features(obs, precision).detach()
                value = agent.value(obs, x).view(-1)
                v_loss = 0.5 * ((value - batch["returns"][idx]) ** 2).mean()
                loss = args.vf_coef * v_loss
            else:
                loss = pg_loss - args.ent_coef * ent + args.vf_coef * v_loss
                if args.kl_coef > 0:
                    kl_base = agent.kl_to_base(obs, mean).mean()
                    loss = loss + args.kl_coef * kl_base
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
            stats = dict(
                policy_loss=pg_loss.item(),
                value_loss=v_loss.item(),
                entropy=ent.item(),
                old_approx_kl=old_approx_kl.item(),
                approx_kl=approx_kl.item(),
                loss=loss.item(),
            )
            if not critic_only and args.kl_coef > 0:
                stats["kl_to_base"] = kl_base.item()
        if not critic_only and args.target_kl is not None and approx_kl > args.target_kl:
            break
    stats["clipfrac"] = float(np.mean(clipfracs)) if clipfracs else 0.0
    return stats


def bootstrap_mask(info: dict, term: torch.Tensor) -> torch.Tensor:
    """Envs whose episode just ended and whose final observation's value is bootstrapped.

    Truncated and successful episodes are (ManiSkill's convention: success is an absorbing max-reward
    state; without it a staged reward pays more for holding the object than for delivering it); failed
    ones are not: a collision has no future. ManiSkill's ppo.py bootstraps failures too.
    """
    return info["_final_info"].bool() & ~terminated_with(info, term, "fail")


def succeeded_mask(info: dict, term: torch.Tensor) -> torch.Tensor:
    """Envs whose episode just ended in success: with ``--absorbing-success`` their final observation is worth
    the absorbing state's ``reward_scale / (1 - gamma)``. Nothing follows a success in training, so the critic's
    estimate there is a guess, and a guess below holding the object makes letting go look worse than holding on
    (docs/notes/rl-from-the-reward.md). A delivery in the step that collides is a failure (the reward pays 0 and
    :func:`bootstrap_mask` gives it no future), so it is not absorbing either."""
    return terminated_with(info, term, "success") & bootstrap_mask(info, term)


def terminated_with(info: dict, term: torch.Tensor, event: str) -> torch.Tensor:
    """Envs whose episode just ended by termination with ``final_info[event]`` set (none if the task has no such
    event)."""
    done = info["_final_info"].bool()
    flag = info["final_info"].get(event)
    return done & term.to(done.device).bool() & (flag.bool() if flag is not None else torch.zeros_like(done))


def compute_gae(rewards, values, dones, next_value, next_done, final_values, args: Args):
    """GAE; ``final_values[t]``: value of the final observation of an episode that ended at step t by
    truncation or success (0 elsewhere, e.g. after a failure)."""
    T = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    lastgaelam = 0
    for t in reversed(range(T)):
        if t == T - 1:
            next_not_done, nextvalues = 1.0 - next_done, next_value
        else:
            next_not_done, nextvalues = 1.0 - dones[t + 1], values[t + 1]
        real_next_values = next_not_done * nextvalues + final_values[t]
        delta = rewards[t] + args.gamma * real_next_values - values[t]
        lastgaelam = delta + args.gamma * args.gae_lambda * next_not_done * lastgaelam
        advantages[t] = lastgaelam
    return advantages, advantages + values


class Rollout:
    """PPO's on-policy storage: ``--num-steps`` steps of the ``--num-envs`` envs, and the envs' current observation
    carried from one rollout to the next."""

    def __init__(self, envs, next_obs: dict, args: Args, device, fresh: bool = False):
        self.envs, self.args, self.device, self.fresh = envs, args, device, fresh
        self.next_obs, self.next_done = next_obs, torch.zeros(args.num_envs, device=device)
        self.allocate()
        self.tracker = EpisodeTracker(args.num_envs, device)

    def allocate(self) -> None:
        """The rollout's storage, which the batch :meth:`collect` returns views of."""
        T, N, device = self.args.num_steps, self.args.num_envs, self.device
        self.obs = {k: torch.zeros((T,) + v.shape, dtype=v.dtype, device=device) for k, v in self.next_obs.items()}
        self.actions = torch.zeros((T, N) + self.envs.single_action_space.shape, device=device)
        self.logprobs, self.rewards, self.dones, self.values, self.final_values = (
            torch.zeros((T, N), device=device) for _ in range(5)
        )

    def collect(
        self,
        agent: Agent,
        recent: dict[str, list[float]],
        generator: Optional[torch.Generator] = None,
        stop: Optional[threading.Event] = None,
    ) -> tuple[dict, float]:
        """One rollout of the sampling policy: the flat batch :func:`ppo_update` trains on, with GAE's advantages
        and returns, and the seconds spent stepping the envs. Finished episodes' metrics go to ``recent``. The
        run's step counter moves when the iteration is done (:func:`train`), not here: a run stopped mid-rollout
        saves counters that match the iterations its weights have trained. ``fresh`` (the constructor's): new
        storage for every rollout, so a batch still being trained on is not overwritten by the next (``--overlap``);
        ``generator``: the actions' random numbers; ``stop``: set, the rollout ends with :class:`CollectionStopped`
        before its next env step."""
        args, device, envs = self.args, self.device, self.envs
        if self.fresh:
            self.allocate()
        agent.eval()
        self.final_values.zero_()
        sim_time = 0.0
        for step in range(args.num_steps):
            if stop is not None and stop.is_set():
                raise CollectionStopped()
            for k in self.obs:
                self.obs[k][step] = self.next_obs[k]
            self.dones[step] = self.next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(self.next_obs, generator=generator)
            self.values[step] = value.flatten()
            self.actions[step], self.logprobs[step] = action, logprob
            ts = time.perf_counter()
            o, reward, term, trunc, info = envs.step(action if envs.device.type == device.type else action.cpu())
            sim_time += time.perf_counter() - ts
            self.next_obs = obs_to(flatten_obs(o), device)
            done = (term | trunc).to(device)
            self.next_done = done.float()
            self.rewards[step] = reward.to(device).view(-1) * args.reward_scale
            if "final_info" in info:
                mask = bootstrap_mask(info, term).to(device)
                if mask.any():
                    fin = obs_to(flatten_obs(info["final_observation"]), device)
                    with torch.no_grad():
                        self.final_values[step, mask] = agent.get_value({k: v[mask] for k, v in fin.items()}).view(-1)
                if args.absorbing_success:
                    absorbing = args.reward_scale / (1 - args.gamma)
                    self.final_values[step, succeeded_mask(info, term).to(device)] = absorbing
            for k, v in self.tracker.update(info.get("final_info", info), done).items():
                recent[k] += v
        with torch.no_grad():
            next_value = agent.get_value(self.next_obs).reshape(1, -1)[0]
            advantages, returns = compute_gae(
                self.rewards, self.values, self.dones, next_value, self.next_done, self.final_values, args
            )
        batch = dict(
            obs={k: v.reshape((-1,) + v.shape[2:]) for k, v in self.obs.items()},
            actions=self.actions.reshape((-1,) + envs.single_action_space.shape),
            logprobs=self.logprobs.reshape(-1),
            advantages=advantages.reshape(-1),
            returns=returns.reshape(-1),
            values=self.values.reshape(-1),
        )
        return batch, sim_time


class CollectionStopped(Exception):
    """A rollout ended before its last step by :meth:`Collector.abort`."""


class Collector:
    """``--overlap``: rollouts collected in a thread while the learner updates on the last one.

    The thread acts with a snapshot of the learner's weights (``actor``, running normaliser included) taken
    before the update it overlaps, so the rollout trained on in iteration k+1 was sampled by the weights of
    iteration k-1, one update behind the ones that train on it; its stored log-probabilities and values are the
    snapshot's, so PPO's ratio is against the policy that acted. The thread's time is spent waiting on the env
    workers' pipes and in torch ops, which release the GIL; both threads run torch on this process's one intra-op
    thread (``one_thread_beside_workers``). The actions draw from a generator of their own, so the update's
    minibatch permutations do not depend on how the two threads interleave.

    Nothing is in flight between iterations (:meth:`join` ends each), so checkpoints, evaluations and the loop's
    bookkeeping see a still run; the one rollout collected ahead (``ready``) is not counted until it is trained
    on, so a run stopped or saved there counts only the env steps it trained, and ``--resume`` collects anew."""

    def __init__(self, rollout: Rollout, agent: Agent, seed: int):
        self.rollout = rollout
        self.actor = copy.deepcopy(agent)
        self.generator = torch.Generator(device=rollout.device).manual_seed(seed)
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ppo-collector")
        self.stop = threading.Event()
        self.pending = None
        self.ready: Optional[tuple] = None

    def _collect(self) -> tuple[dict, float, dict, float]:
        recent: dict[str, list[float]] = defaultdict(list)
        t = time.perf_counter()
        batch, sim_time = self.rollout.collect(self.actor, recent, self.generator, self.stop)
        return batch, sim_time, recent, time.perf_counter() - t

    def take(self, agent: Agent) -> tuple[dict, float, dict, float]:
        """(batch, seconds stepping the envs, finished episodes' metrics, seconds collecting) of the rollout the
        next update trains on: the one collected during the last update, or with none (the first iteration, and
        the first after a ``--resume``) one collected now by ``agent``'s weights."""
        if self.ready is None:
            self.actor.load_state_dict(agent.state_dict())
            self.ready = self._collect()
        out, self.ready = self.ready, None
        return out

    def launch(self, agent: Agent) -> None:
        """Starts the next rollout in the thread, acting with ``agent``'s weights as they are now."""
        assert self.pending is None and self.ready is None, "a rollout is already collected or in flight"
        self.actor.load_state_dict(agent.state_dict())
        self.pending = self.pool.submit(self._collect)

    def join(self) -> None:
        """Waits for the rollout in flight, the next :meth:`take`'s (an error of the collection is raised here)."""
        future, self.pending = self.pending, None
        if future is None:
            return
        try:
            self.ready = future.result()
        except KeyboardInterrupt:  # in this thread, while it waited: stop the collection before the envs close
            self.stop.set()
            wait_for([future])
            raise

    def abort(self) -> None:
        """Stops the rollout in flight at its next env step and waits for it; nothing is kept."""
        future, self.pending, self.ready = self.pending, None, None
        if future is not None:
            self.stop.set()
            wait_for([future])
            self.stop.clear()

    def close(self) -> None:
        self.abort()
        self.pool.shutdown(wait=True)


# ----------------------------------------------------------------------------- checkpoints
FORMAT = "maniskill_irb120.ppo/1"


def save_checkpoint(path: Path, agent: Agent, optimizer, counters: dict, args: Args) -> None:
    atomic_save(
        checkpoint(
            FORMAT,
            args,
            counters,
            model=agent.state_dict(),
            optimizer=optimizer.state_dict(),
            signature=agent.signature(),
            policy=policy_section(
                "ppo",
                agent,
                dict(agent.signature(), init_logstd=agent.init_logstd),
                env_id=args.env_id,
                obs=args.obs,
                action_frame=args.action_frame,
                control_mode=args.control_mode,
                reward_mode=args.reward_mode,
                env_kwargs=args.env_kwargs,
            ),
        ),
        path,
    )


def prune_checkpoints(ckpt_dir: Path, keep: int) -> list[Path]:
    """Removes all but the ``keep`` newest ``ckpt_N.pt`` (by N) and returns what it removed. A camera run writes
    a 17 MB checkpoint every ``--save-freq`` iterations, gigabytes over a long run; ``latest.pt`` (what --resume
    continues) and ``best.pt`` (what selection kept) are other names and never touched."""
    if keep <= 0:
        return []
    numbered = sorted(
        (int(p.stem.split("_", 1)[1]), p) for p in ckpt_dir.glob("ckpt_*.pt") if p.stem.split("_", 1)[1].isdigit()
    )
    removed = [p for _, p in numbered[:-keep]]
    for p in removed:
        p.unlink()
    return removed


def read_checkpoint(path: Path, args: Args) -> dict:
    """A PPO checkpoint, refused when it acted in another frame than ``--action-frame``."""
    ckpt = load_torch(path, FORMAT, "agents.ppo")  # migrated: its args name its frame
    frame = ckpt["args"]["action_frame"]
    if frame != args.action_frame:
        raise ValueError(f"checkpoint {path} acts in the {frame!r} frame; pass --action-frame {frame}")
    return ckpt


def load_checkpoint(path: Path, agent: Agent, args: Args, ckpt: Optional[dict] = None) -> dict:
    ckpt = ckpt if ckpt is not None else read_checkpoint(path, args)
    if ckpt["signature"] != agent.signature():
        raise signature_mismatch(
            f"checkpoint {path} (obs={args.obs}, env={args.env_id}, control_mode={args.control_mode})",
            ckpt["signature"],
            agent.signature(),
            args,
        )
    agent.load_state_dict(ckpt["model"])
    return ckpt


# ----------------------------------------------------------------------------- evaluation
def evaluate(agent: Agent, envs, num_episodes: int, device) -> dict:
    """Deterministic policy on the eval envs until ``num_episodes`` episodes finish."""
    obs, _ = envs.reset()
    stats: dict[str, list[float]] = defaultdict(list)
    tracker = EpisodeTracker(envs.num_envs, envs.device)  # sums stay on the env's device: no per-step copies
    finished = 0
    while finished < num_episodes:
        with torch.no_grad():
            action = agent.get_action(obs_to(flatten_obs(obs), device), deterministic=True)
        obs, rew, term, trunc, info = envs.step(action.cpu() if envs.device.type == "cpu" else action)
        done = (term | trunc).to(torch.bool)
        for k, v in tracker.update(info.get("final_info", info), done).items():
            stats[k] += v
        finished += int(done.sum())
    summary = {f"{k}_mean": float(np.mean(v)) for k, v in stats.items()}
    summary["episodes"] = finished
    return summary


# ----------------------------------------------------------------------------- main loop
def run_evaluation_only(args: Args) -> dict:
    """``--evaluate``: the deterministic policy on ``--eval-episodes`` held-out seeds, scored as the benchmark and
    the other trainers score a run (agents.common)."""
    device = resolve_device(args.device)

    def load(path: Path) -> tuple[Agent, dict]:
        ckpt = read_checkpoint(path, args)
        envs = make_envs(args, 1, evaluate=True)  # its spaces size the agent
        try:
            sig = ckpt["signature"]  # its critic as trained (an evaluation acts without it)
            trained = replace(
                args,
                critic_obs=sig.get("critic_obs", "same"),
                encoder=sig.get("encoder", "nature"),
                base_checkpoint=None,
            )
            agent = agent_for(envs, device, trained, residual=sig["residual"], privileged_dim=sig.get("privileged_dim"))
        finally:
            envs.close()
        load_checkpoint(path, agent, args, ckpt)
        return agent, ckpt

    return evaluate_checkpoint(
        args, load, lambda agent, videos: final_evaluation(agent, args, device, videos), adopt=()
    )


def read_resume(path: Path, args: Args) -> dict:
    """The checkpoint ``--resume`` continues from."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"--resume: checkpoint {path} does not exist")
    return read_checkpoint(path, args)


class PPO(Algorithm):
    """PPO's part of a run (agents.common.loop): a step is one iteration, a rollout of ``--num-steps`` per env and
    its update; the envs reset once, then every rollout continues where the last stopped."""

    name, step_key = "ppo", "iteration"

    def __init__(self, args: Args):
        super().__init__(args)
        self.counters = dict(env_steps=0, iteration=0)
        self.device = resolve_device(args.device)
        self.eval_envs, self.last_eval, self.history, self.recent = None, {}, [], defaultdict(list)
        self.collector: Optional[Collector] = None

    def read(self, path: Path) -> dict:
        return read_resume(path, self.args)

    def build(self, saved: Optional[dict]):
        args = self.args
        torch.backends.cudnn.deterministic = args.torch_deterministic
        self.envs = make_envs(args, args.num_envs)
        init = saved if saved is not None else (read_checkpoint(args.init_policy, args) if args.init_policy else None)
        # resuming (or starting from a PPO checkpoint): the base's weights come with the checkpoint
        base = args.base_checkpoint if init is None else None
        residual = init is not None and init["signature"]["residual"]
        self.agent = agent_for(self.envs, self.device, replace(args, base_checkpoint=base), residual=residual)
        if args.kl_coef > 0 and self.agent.base is None:
            raise ValueError(f"--kl-coef {args.kl_coef}: this run has no base policy (a --base-checkpoint run has one)")
        self.optimizer = optim.Adam(self.agent.parameters(), lr=args.learning_rate, eps=1e-5)
        if saved is not None:
            check_resume_signature(saved, self.agent.signature(), args.resume, args)
            self.agent.load_state_dict(saved["model"])
            self.optimizer.load_state_dict(saved["optimizer"])
        elif args.init_policy is not None:
            load_checkpoint(args.init_policy, self.agent, args, init)
        return self.envs

    def start(self) -> None:
        self.first_iteration = self.counters["iteration"]
        total = env_step_budget(self.args)
        self.iterations = -(-total // self.args.batch_size) if total else None  # the last starts below the budget
        next_obs, _ = self.envs.reset(seed=self.args.seed + self.counters["iteration"])
        overlap = self.args.overlap
        self.rollout = Rollout(self.envs, obs_to(flatten_obs(next_obs), self.device), self.args, self.device, overlap)
        if overlap:
            torch.set_num_threads(1)  # the learner and the collector each on one (main restores the count)
            seed = self.args.seed * 1_000_003 + self.counters["iteration"]
            self.collector = Collector(self.rollout, self.agent, seed)
        self.t_start = time.perf_counter()

    def step(self, budget: Budget) -> dict:
        args, agent, optimizer, counters = self.args, self.agent, self.optimizer, self.counters
        it = counters["iteration"] + 1
        t0 = time.perf_counter()
        if args.anneal_lr:
            optimizer.param_groups[0]["lr"] = (1.0 - (it - 1.0) / self.iterations) * args.learning_rate
        collector = self.collector
        if collector is None:
            batch, sim_time = self.rollout.collect(agent, self.recent)
        else:  # the rollout collected during the last update; the next one starts now, beside this update
            batch, sim_time, recent, _ = collector.take(agent)
            for k, v in recent.items():
                self.recent[k] += v
            if self.iterations is None or it < self.iterations:  # the last iteration collects nothing untrained
                collector.launch(agent)
        if agent.critic_norm is not None:  # the critic's statistics before its update (the actor's never read them)
            agent.critic_norm.update(batch["obs"][PRIVILEGED])
        agent.train()
        tu = time.perf_counter()
        try:
            stats = ppo_update(agent, optimizer, batch, args, critic_only=it <= args.critic_warmup_iters)
            if agent.norm is not None:  # after the update: the rollout's log-probabilities used the old statistics
                agent.norm.update(batch["obs"]["state"])
        except BaseException:
            if collector is not None:
                collector.abort()
            raise
        update_time = time.perf_counter() - tu
        if collector is not None:
            collector.join()  # nothing in flight between iterations: saves and evaluations see still envs
        counters["iteration"] = it
        counters["env_steps"] += args.batch_size
        dt = time.perf_counter() - t0
        y_pred, y_true = batch["values"].cpu().numpy(), batch["returns"].cpu().numpy()
        var_y = np.var(y_true)
        scalars = {f"losses/{k}": v for k, v in stats.items()}
        scalars.update(
            {
                "charts/SPS": args.batch_size / dt,
                "charts/learning_rate": optimizer.param_groups[0]["lr"],
                "losses/explained_variance": float("nan") if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y,
                "time/rollout_s": dt - update_time,
                "time/sim_s": sim_time,
                "time/update_s": update_time,
            }
        )
        scalars.update({f"train/{k}": float(np.mean(v)) for k, v in self.recent.items()})
        self.history.append(
            dict(iteration=it, global_step=counters["env_steps"], wall_s=time.perf_counter() - self.t_start, **scalars)
        )
        self.recent.clear()
        if args.eval_freq and it % args.eval_freq == 0:
            self.periodic_evaluation()
        return scalars

    def periodic_evaluation(self) -> None:
        """``--eval-freq-episodes`` episodes on the periodic evaluation's envs, logged as ``eval/``."""
        args = self.args
        if self.eval_envs is None:
            videos = self.run_dir / "videos" if args.capture_video else None
            self.eval_envs = make_envs(args, args.num_eval_envs, evaluate=True, video_dir=videos)
        self.agent.eval()
        self.last_eval = evaluate(self.agent, self.eval_envs, args.eval_freq_episodes, self.device)
        self.logger.scalars({f"eval/{k}": v for k, v in self.last_eval.items()}, self.counters["env_steps"])

    def postfix(self, scalars: dict) -> dict:
        success = scalars.get("train/success_rate")
        return dict(SPS=f"{scalars['charts/SPS']:.0f}", success="-" if success is None else f"{success:.2f}")

    def save(self, path: Path, counters: dict) -> None:
        save_checkpoint(path, self.agent, self.optimizer, counters, self.args)

    def save_periodic(self, ckpt_dir: Path, counters: dict, last: bool) -> None:
        it = counters["iteration"]
        if it % self.args.save_freq == 0 or last:
            self.save(ckpt_dir / f"ckpt_{it}.pt", counters)
            self.save(ckpt_dir / "latest.pt", counters)
            prune_checkpoints(ckpt_dir, self.args.keep_checkpoints)

    def load_selected(self, path: Path) -> None:
        load_checkpoint(path, self.agent, self.args)

    def evaluate(self, args: Args, video_dir: Optional[Path] = None, first_seed: int = EVAL_SEED) -> dict:
        return final_evaluation(self.agent, args, self.device, video_dir, first_seed)

    def selected(self, best: dict) -> dict:
        return dict(iteration=best["iteration"], global_step=best["env_steps"])

    def summary(self) -> dict:
        c = self.counters
        its = dict(iterations=c["iteration"], iterations_this_run=c["iteration"] - self.first_iteration)
        return dict(global_step=c["env_steps"], **its, last_eval=self.last_eval)

    def close(self) -> None:
        if self.collector is not None:
            self.collector.close()
        if self.eval_envs is not None:
            self.eval_envs.close()


def train(args: Args) -> dict:
    """A PPO run; its result also carries every iteration's scalars (``history``, not in summary.json)."""
    ppo = PPO(args)
    result = loop.run(ppo, Clock)
    result["history"] = ppo.history
    return result


def final_evaluation(
    agent: Agent, args: Args, device, video_dir: Optional[Path] = None, first_seed: int = EVAL_SEED
) -> dict:
    """The deterministic policy on held-out seeds (or, for checkpoint selection, on validation seeds), scored like
    every other trainer (agents.common)."""
    agent.eval()
    return held_out_evaluation(
        lambda obs: agent.get_action(obs_to(obs, device), deterministic=True).cpu(),
        args,
        video_dir,
        first_seed,
        reward_mode=args.reward_mode,
        control_mode=args.control_mode,
    )


def main(args: Args) -> dict:
    check_budget(args)
    resolve_precision(args.precision, resolve_device(args.device))  # bf16 without native support: refused here
    if not args.evaluate and args.norm_adv and args.minibatch_size < 2:
        raise ValueError(
            f"--num-envs {args.num_envs} x --num-steps {args.num_steps} / --num-minibatches {args.num_minibatches} "
            "gives minibatches of fewer than 2 rows: their advantages cannot be normalised (std of one value is NaN)"
        )
    if args.kl_coef < 0:
        raise ValueError(f"--kl-coef must be >= 0, got {args.kl_coef}")
    if args.keep_checkpoints < 0:
        raise ValueError(f"--keep-checkpoints must be >= 0 (0 keeps every one), got {args.keep_checkpoints}")
    if args.evaluate and args.eval_episodes < 1:
        raise ValueError(
            f"--evaluate scores --eval-episodes N held-out episodes; give N >= 1, got {args.eval_episodes}"
        )
    if not args.evaluate and args.checkpoint is not None:
        raise ValueError("--checkpoint is what --evaluate reads; a new run starts from a checkpoint with --init-policy")
    if args.anneal_lr and args.total_env_steps is None:
        raise ValueError("--anneal-lr anneals the learning rate over --total-env-steps: give it")
    if args.absorbing_success and args.reward_mode != "normalized_dense":
        raise ValueError(
            f"--absorbing-success values success at 1 a step, the normalized_dense reward's; --reward-mode is "
            f"{args.reward_mode!r}"
        )
    if args.kl_coef > 0 and args.base_checkpoint is None and args.resume is None and args.init_policy is None:
        raise ValueError("--kl-coef keeps the policy near a base policy: give --base-checkpoint DAGGER.pt")
    with torch_threads(torch.get_num_threads()):  # the CPU workers' one learner thread ends with the run
        return run_evaluation_only(args) if args.evaluate else train(args)


if __name__ == "__main__":
    entry(Args, "agents.ppo", main)
