"""DAgger with DART noise, from state or from the RGB-D camera: round 0 records the noisy scripted expert, every
later round the learner (mixed with the expert by a decaying beta), the reactive expert (or ``--teacher``, a trained
state policy) labelling each state it reached; the policy trains on the aggregated dataset. This file is DAgger's
part only (:class:`DAgger`); the run around it is agents.common.loop's. See docs/training.md.

    python -m agents.dagger --recipe dagger-state --total-env-steps 205835
    python -m agents.dagger --resume runs/NAME/checkpoints/latest.pt
    python -m agents.dagger --evaluate --checkpoint runs/NAME/checkpoints/latest.pt
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn.functional as F

import maniskill_irb120  # noqa: F401  (registers the envs)
from agents.common import (
    EVAL_SEED,
    Clock,
    Dataset,
    EpisodeTracker,
    RunArgs,
    atomic_save,
    autocast,
    aux_dim,
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
    prune_row_files,
    resolve_device,
    resolve_precision,
    restore_dataset,
    shapes_of,
    torch_threads,
    train_seed,
)
from agents.common.args import resumed_args
from agents.common.loop import Algorithm
from maniskill_irb120.policies import policy_module, policy_section, read_policy_section, section_of
from maniskill_irb120.policies.nets import DeterministicActor, drop_rgb, jitter_rgb, random_shift

FORMAT = "maniskill_irb120.dagger/1"


@dataclass
class Args(RunArgs):
    obs: Literal["state", "rgbd"] = "state"
    """state: privileged state vector; rgbd: 84x84 RGB-D hand camera + proprioception"""
    action_frame: Literal["world", "tool"] = "world"
    """world: translation in world axes (WorldFrameToolAction); tool: the raw tool-frame action"""
    obs_without: tuple[str, ...] = ()
    """observation keys the policy does not see, e.g. agent/qvel (DropObservationKeys)"""
    num_envs: int = 2
    """episode collectors: CPU envs (env 0 here, the others in worker processes), or one GPU-batched env's size"""
    expert_episodes: int = 50
    """round 0: noisy expert episodes"""
    dart_noise: float = 0.2
    """round 0: std of the Gaussian added to the expert's arm actions (in action units, limits ±1)"""
    episodes_per_round: int = 10
    """later rounds: learner episodes labelled by the expert"""
    beta: float = 0.5
    """round 1's probability that a step executes the expert's action instead of the learner's"""
    beta_decay: float = 0.7
    """beta is multiplied by this every round"""
    learner_noise: float = 0.05
    """std of the Gaussian added to the learner's arm actions (widens the states it labels)"""
    updates_per_round: int = 1000
    """minibatch updates on the whole aggregated dataset after each round"""
    initial_updates: int = 0
    """round 0's updates on the expert's episodes (0: --updates-per-round)"""
    batch_size: int = 256
    """minibatch size"""
    learning_rate: float = 1e-3
    """AdamW learning rate (MSE to the expert's actions)"""
    weight_decay: float = 1e-5
    """AdamW weight decay"""
    encoder: Literal["nature", "keypoints", "keypoints-depth"] = "nature"
    """rgbd image encoder: nature (NatureCNN), keypoints (KeypointCNN: conv + spatial softmax) or keypoints-depth (a
    depth-only keypoint stack beside it; --init-policy widens a keypoints policy into it, acting as that one did)"""
    augment: bool = True
    """rgbd: DrQ random-shift augmentation of the images while training"""
    rgb_dropout: float = 0.0
    """rgbd: probability a training sample's RGB image is blacked out, its depth kept (modality dropout), so the
    policy must localise from the depth too (0: off)"""
    color_jitter: float = 0.0
    """rgbd: strength of each training sample's own colour jitter (brightness, contrast and saturation in 1 ± it,
    hue rotated by up to it x 180 deg), so the policy cannot rest on the surfaces' absolute colours (0: off)"""
    aux_weight: float = 0.0
    """weight of the auxiliary loss on privileged targets (0: off)"""
    aux_mount: bool = False
    """the auxiliary targets include the camera's drawn offset from its nominal mount, so the encoder learns to read
    the mount off where the fingers appear (with a camera_pos/camera_rot randomisation; needs --aux-weight)"""
    capacity: int = 300_000
    """most transitions kept (oldest dropped first); rgbd frames take ~35 kB each"""
    init_policy: Optional[Path] = None
    """start the policy from this agents.dagger checkpoint's or exported policy's weights (same task, observation,
    encoder and action frame); optimiser, dataset and counters start fresh, e.g. to train a nominal policy on
    under --env-kwargs randomization. Such a run resumes with --resume alone, from its own weights. The policy keeps
    its state normalisation: round 0's episodes do not refit it"""
    init_data: Optional[Path] = None
    """start the dataset with another agents.dagger run's (its checkpoints/latest.pt, the row files beside it): the
    same task, observation, action frame, labeller (--teacher) and auxiliary targets, any randomisation; e.g. a
    student of another encoder trained on the states a run already collected and labelled. Those rows count toward
    neither this run's env steps nor its budget. Such a run resumes with --resume alone"""
    save_freq: int = 10
    """checkpoint every N rounds, and always at the end; the dataset goes beside it, each save writing only
    the rows new since the last (checkpoints/data/)"""
    teacher: Optional[Path] = None
    """a trained state policy (an agents.ppo, agents.sac or agents.dagger checkpoint, or an exported policy, of this
    task and control mode, obs state) labels the states in place of the scripted expert: teacher–student, the camera
    student imitating a teacher that learned from the reward alone"""
    precision: Literal["fp32", "bf16", "auto"] = "fp32"
    """the encoder in the updates: bf16 autocast (its convolutions about twice as fast on a CPU with native bf16;
    weights, heads, losses and checkpoints stay fp32; agents/common/precision.py), fp32, or auto (bf16 on a
    CPU with native bf16, else fp32)"""


make_envs = labelled_envs
"""this run's envs, each state labelled (agents.common.envs.labelled_envs)"""


def collect(envs, state: dict, policy, data: Dataset, episodes: int, beta: float, noise: float, device) -> dict:
    """Step ``envs`` until ``episodes`` episodes end: each step executes the expert's action with probability
    ``beta`` (else the learner's), plus Gaussian noise on the arm; every visited state is stored with the
    expert's clean label. ``state`` carries the envs' current obs and labels between calls."""
    n = envs.num_envs
    tracker = EpisodeTracker(n, torch.device("cpu"))
    stats: dict[str, list[float]] = defaultdict(list)
    finished = steps = 0
    while finished < episodes:
        obs, label = state["obs"], state["label"]
        data.add(obs, label, state.get("aux"))
        action = label.clone()
        if beta < 1.0:
            with torch.no_grad():
                learner = policy(obs_to(obs, device)).cpu()
            use_learner = torch.rand(n) >= beta
            action[use_learner] = learner[use_learner]
        action[:, :4] += noise * torch.randn(n, 4)
        o, _, term, trunc, info = envs.step(action.clamp(-1, 1))
        done = (term | trunc).bool()
        state.update(labels(o, info))
        for k, v in tracker.update(info.get("final_info", info), done).items():
            stats[k] += v
        finished += int(done.sum())
        steps += n
    out = {k: float(np.mean(v)) for k, v in stats.items()}
    out["steps"] = steps
    return out


def labels(obs, info: dict) -> dict:
    """What ``collect`` carries from one step to the next: the observation and the worker's labels."""
    out = dict(obs=flatten_obs(obs), label=info["expert_action"].float())
    if "expert_aux" in info:
        out["aux"] = info["expert_aux"].float()
    return out


def train_round(
    policy,
    optimizer,
    data: Dataset,
    args: Args,
    device,
    out_of_time=lambda: False,
    aux_head=None,
    updates=None,
    precision: str = "fp32",
) -> dict[str, float]:
    """``updates`` (default ``updates_per_round``) minibatch steps of behaviour cloning (MSE to the expert's
    actions), plus ``aux_weight`` x the auxiliary head's MSE when there is one; fewer when ``out_of_time()``
    (the wall-clock budget: from the camera, 1000 updates take minutes on 2 cores). ``precision``: a resolved
    ``--precision`` (fp32 or bf16) for the encoder; the heads and the losses are float32. Mean losses."""
    policy.train()
    sums, done = defaultdict(float), 0
    for _ in range(updates or args.updates_per_round):
        if done and out_of_time():
            break
        obs, act, aux = data.sample_with_aux(args.batch_size, device)
        if args.obs == "rgbd" and args.augment:
            obs = random_shift(obs)
        if args.color_jitter > 0:
            obs = jitter_rgb(obs, args.color_jitter)
        if args.rgb_dropout > 0:
            obs = drop_rgb(obs, args.rgb_dropout)
        with autocast(precision, device):  # the encoder only: the convolutions are the cost
            feats = policy.features(obs)
        feats = feats.float()
        loss = bc = F.mse_loss(torch.tanh(policy.head(feats)), act)
        if aux_head is not None:
            aux_loss = F.mse_loss(aux_head(feats), aux)
            loss = loss + args.aux_weight * aux_loss
            sums["aux"] += aux_loss.item()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        sums["bc"] += bc.item()
        done += 1
    policy.eval()
    return {k: v / max(1, done) for k, v in sums.items()}


def policy_for(space, action_dim: int, device, encoder: str = "nature") -> DeterministicActor:
    image_shape, state_dim = shapes_of(space)
    return DeterministicActor(image_shape, state_dim, action_dim, encoder=encoder).to(device)


def aux_head_for(policy: DeterministicActor, device, mount: bool = False) -> torch.nn.Module:
    """A small MLP from the policy's features to the :func:`privileged_aux` targets (training only)."""
    n, out = policy.encoder.out_dim, aux_dim(mount)
    return torch.nn.Sequential(torch.nn.Linear(n, 256), torch.nn.ReLU(), torch.nn.Linear(256, out)).to(device)


def save(path: Path, policy, optimizer, data: Dataset, counters: dict, args: Args, aux_head=None, rows=None) -> dict:
    """The checkpoint, with the dataset as files of the rows new since the last save beside it in ``data/``
    (``rows``: the last save's manifest): returns the new manifest."""
    rows = data.save_new_rows(path.parent / "data", rows)
    aux = aux_head.state_dict() if aux_head is not None else None
    write(path, policy, counters, args, aux_head=aux, optimizer=optimizer.state_dict(), data_rows=rows)
    prune_row_files(path.parent / "data", rows)
    return rows


def save_selected(path: Path, policy, counters: dict, args: Args) -> None:
    """``best.pt``: the selected policy with the run's counters and arguments, for ``--evaluate`` and export; no
    optimiser and no dataset, so it is a policy to deploy, not a run to continue (``--resume`` refuses it)."""
    write(path, policy, counters, args)


def write(path: Path, policy, counters: dict, args: Args, **state) -> None:
    """A checkpoint of ``policy`` with ``state`` beside it, and the policy section that ``--evaluate``, export and
    the robot read."""
    signature = policy.signature()
    section = policy_section(
        "dagger",
        policy,
        signature,
        env_id=args.env_id,
        obs=args.obs,
        action_frame=args.action_frame,
        obs_without=args.obs_without,
        env_kwargs=args.env_kwargs,
    )
    model = policy.state_dict()
    atomic_save(checkpoint(FORMAT, args, counters, model=model, signature=signature, policy=section, **state), path)


def load_policy(path: Path, device) -> tuple[DeterministicActor, dict]:
    """A trained DAgger policy (eval mode) and its checkpoint dict."""
    ckpt = load_for_evaluation(path, FORMAT, "agents.dagger", "dagger")
    return policy_module(section_of(ckpt, str(path)), device), ckpt


def final_evaluation(policy, args: Args, device, video_dir: Optional[Path], first_seed: int = EVAL_SEED) -> dict:
    return held_out_evaluation(lambda o: policy(obs_to(o, device)).cpu(), args, video_dir, first_seed)


def run_evaluation_only(args: Args) -> dict:
    device = resolve_device(args.device)
    return evaluate_checkpoint(
        args,
        lambda path: load_policy(path, device),
        lambda policy, videos: final_evaluation(policy, args, device, videos),
    )


def load_initial_weights(args: Args, policy: DeterministicActor) -> None:
    """Load ``--init-policy``'s weights, once its section says it reads and acts as this run's policy does; a
    ``keypoints`` policy into a ``keypoints-depth`` run is widened (:meth:`DeterministicActor.widen`)."""
    where = f"--init-policy {args.init_policy}"
    section = read_policy_section(args.init_policy, where)
    theirs = dict(
        kind=section["kind"],
        env_id=section["env_id"],
        obs=section["obs"],
        action_frame=section["action_frame"],
        obs_without=tuple(section["obs_without"]),
        signature=section["config"],
    )
    ours = dict(kind="dagger", env_id=args.env_id, obs=args.obs, action_frame=args.action_frame)
    ours.update(obs_without=tuple(args.obs_without), signature=policy.signature())
    widens = ours["signature"].get("encoder") == "keypoints-depth" and theirs["signature"].get("encoder") == "keypoints"
    if widens:
        theirs["signature"] = dict(theirs["signature"], encoder="keypoints-depth")
    differ = [f"{k}={theirs[k]!r} (this run: {ours[k]!r})" for k in ours if theirs[k] != ours[k]]
    if differ:
        raise ValueError(f"{where} is not this run's policy: " + ", ".join(differ))
    if widens:
        policy.widen(section["state_dict"])
    else:
        policy.load_state_dict(section["state_dict"])


def initial_data(args: Args) -> dict:
    """``--init-data``'s checkpoint, once that run's arguments say its rows are this run's kind (the same
    observation and action, labelled by the same labeller, with the same auxiliary targets) and it holds a dataset.
    Read before any env starts: its rows are loaded once the run is built."""
    where = f"--init-data {args.init_data}"
    if not Path(args.init_data).is_file():
        raise FileNotFoundError(f"{where}: no such checkpoint")
    theirs = resumed_args(Args, Path(args.init_data))
    names = ("env_id", "obs", "action_frame", "obs_without", "teacher", "aux_mount")
    differ = [
        f"{k}={getattr(theirs, k)!r} (this run: {getattr(args, k)!r})"
        for k in names
        if getattr(theirs, k) != getattr(args, k)
    ]
    if (theirs.aux_weight > 0) != (args.aux_weight > 0):
        differ.append(f"aux targets {'on' if theirs.aux_weight > 0 else 'off'} (this run: the other)")
    if differ:
        raise ValueError(f"{where} holds rows of another kind: " + ", ".join(differ))
    saved = load_torch(Path(args.init_data), FORMAT, "agents.dagger")
    if "optimizer" not in saved:
        raise ValueError(f"{where} holds a selected policy (best.pt), no dataset: give the run's checkpoints/latest.pt")
    return saved


def started_with(resume: Path) -> Args:
    """The arguments the run whose checkpoint is ``resume`` was started with."""
    return resumed_args(Args, Path(resume))


def check_args(args: Args) -> None:
    """Flags that would otherwise be ignored or break a long run late are refused up front, by name."""
    if args.encoder != "nature" and args.obs != "rgbd":
        raise ValueError(f"--encoder {args.encoder} reads the camera; --obs {args.obs} has no image")
    if not (args.aux_weight >= 0 and np.isfinite(args.aux_weight)):
        raise ValueError(f"--aux-weight must be a finite number >= 0, got {args.aux_weight}")
    if not 0 <= args.rgb_dropout < 1:
        raise ValueError(f"--rgb-dropout is a probability in [0, 1), got {args.rgb_dropout}")
    if args.rgb_dropout > 0 and args.obs != "rgbd":
        raise ValueError(f"--rgb-dropout blacks out camera images; --obs {args.obs} has none")
    if not 0 <= args.color_jitter <= 1:  # NaN fails both comparisons
        raise ValueError(f"--color-jitter is a strength in [0, 1], got {args.color_jitter}")
    if args.color_jitter > 0 and args.obs != "rgbd":
        raise ValueError(f"--color-jitter changes camera images' colours; --obs {args.obs} has none")
    if args.aux_mount and args.aux_weight == 0:
        raise ValueError("--aux-mount adds the camera mount to the auxiliary targets: it needs --aux-weight > 0")
    if args.resume is not None and (args.init_policy is not None or args.init_data is not None):
        # a run started from --init-policy or --init-data resumes with it among its own arguments; another one
        # would be ignored
        own = started_with(args.resume)
        if args.init_policy is not None and own.init_policy != args.init_policy:
            raise ValueError("--init-policy starts a new run from a policy's weights; --resume continues one: pick one")
        if args.init_data is not None and own.init_data != args.init_data:
            raise ValueError("--init-data starts a new run from a dataset; --resume continues one: pick one")
    elif args.init_data is not None:
        initial_data(args)
    if args.initial_updates < 0:
        raise ValueError(f"--initial-updates must be >= 0 (0: --updates-per-round), got {args.initial_updates}")


class DAgger(Algorithm):
    """DAgger's part of a run (agents.common.loop): a step is a round, its episodes labelled and the policy trained
    further on the aggregated dataset. Round 0 (the noisy expert's episodes) runs whatever the budget: no learner
    exists before it, and its time is no estimate of a learner's round."""

    name, prefix, default_minutes, step_key = "dagger", "dagger__", 60.0, "round"

    def __init__(self, args: Args):
        super().__init__(args)
        self.counters = dict(round=0, env_steps=0, episodes=0, wall_s=0.0)
        self.device = resolve_device(args.device)
        self.precision = resolve_precision(args.precision, self.device)
        self.rows = None  # the manifest of the dataset's row files on disk

    def read(self, path: Path) -> dict:
        saved = load_torch(path, FORMAT, "agents.dagger")
        if "optimizer" not in saved:  # refused before any env worker starts
            raise ValueError(
                f"--resume {path} holds a selected policy (best.pt), not a run to continue: resume from the run's "
                "checkpoints/latest.pt"
            )
        return saved

    def build(self, saved: Optional[dict]):
        args, device = self.args, self.device
        self.learner_threads = torch.get_num_threads()  # before CPU workers claim the cores (make_envs: one thread)
        self.envs = envs = make_envs(args, args.num_envs)
        action_dim = int(np.prod(envs.single_action_space.shape))
        self.policy = policy = policy_for(envs.single_observation_space, action_dim, device, args.encoder)
        self.data = Dataset(args.capacity)
        if saved is None and (args.init_policy is not None or args.init_data is not None):
            try:  # a resumed run has weights and data of its own
                if args.init_policy is not None:
                    load_initial_weights(args, policy)
                if args.init_data is not None:
                    restore_dataset(self.data, initial_data(args), Path(args.init_data).parent / "data")
            except BaseException:
                envs.close()
                raise
        self.aux_head = aux_head = aux_head_for(policy, device, args.aux_mount) if args.aux_weight > 0 else None
        params = list(policy.parameters()) + (list(aux_head.parameters()) if aux_head is not None else [])
        self.optimizer = torch.optim.AdamW(params, lr=args.learning_rate, weight_decay=args.weight_decay)
        if saved is not None:
            check_resume_signature(saved, policy.signature(), args.resume, args)
            if (saved.get("aux_head") is None) != (aux_head is None):
                raise ValueError(
                    f"--resume {args.resume}: the checkpoint and this run disagree on --aux-weight being 0"
                )
            policy.load_state_dict(saved["model"])
            if aux_head is not None:
                targets = saved["aux_head"]["2.bias"].shape[0]
                if targets != aux_dim(args.aux_mount):
                    raise ValueError(
                        f"--resume {args.resume}: the checkpoint's auxiliary head predicts {targets} targets, this "
                        f"run's {aux_dim(args.aux_mount)}: they disagree on --aux-mount"
                    )
                aux_head.load_state_dict(saved["aux_head"])
            self.optimizer.load_state_dict(saved["optimizer"])
            self.rows = saved.get("data_rows")
            restore_dataset(self.data, saved, Path(args.resume).parent / "data")
        return envs

    def start(self) -> None:
        o, info = self.envs.reset(seed=train_seed(self.args.seed, self.counters["round"] * 1000))
        self.state = labels(o, info)

    def must_step(self) -> bool:
        return self.counters["round"] == 0

    def estimates(self) -> bool:
        return self.counters["round"] > 1

    def step(self, budget) -> dict:
        args, counters, device, data, policy = self.args, self.counters, self.device, self.data, self.policy
        r = counters["round"]
        t0 = time.perf_counter()
        if r == 0:  # minutes before the bar's first move from the camera: say what runs and how fast
            updates0 = args.initial_updates or args.updates_per_round
            print(f"[dagger] round 0: {args.expert_episodes} labelled episodes, then {updates0} updates", flush=True)
            stats = collect(self.envs, self.state, policy, data, args.expert_episodes, 1.0, args.dart_noise, device)
            if args.init_policy is None:  # a loaded policy's weights expect its own normalisation
                policy.norm.fit(data.obs["state"][: data.size])
            took = time.perf_counter() - t0
            rate = stats["steps"] / took
            print(f"[dagger] round 0: {stats['steps']:,} env steps in {took:.0f} s ({rate:.0f}/s)", flush=True)
        else:
            beta = args.beta * args.beta_decay ** (r - 1)
            stats = collect(
                self.envs, self.state, policy, data, args.episodes_per_round, beta, args.learner_noise, device
            )
        updates = (args.initial_updates or None) if r == 0 else None
        with torch_threads(self.learner_threads):  # the workers wait through the updates: every core for them
            losses = train_round(
                policy, self.optimizer, data, args, device, budget.out_of_time, self.aux_head, updates, self.precision
            )
        counters["round"] = r + 1
        counters["env_steps"] += stats.pop("steps")
        counters["episodes"] += args.expert_episodes if r == 0 else args.episodes_per_round
        scalars = {f"train/{k}": v for k, v in stats.items()}
        scalars.update({f"losses/{k}": v for k, v in losses.items()})
        scalars.update({"charts/dataset": data.size, "charts/round_s": time.perf_counter() - t0})
        return scalars

    def postfix(self, scalars: dict) -> dict:
        loss, success = scalars.get("losses/bc", 0), scalars.get("train/success_rate", 0)
        return dict(round=self.counters["round"] - 1, data=self.data.size, loss=f"{loss:.4f}", success=f"{success:.2f}")

    def save(self, path: Path, counters: dict) -> None:
        self.rows = save(path, self.policy, self.optimizer, self.data, counters, self.args, self.aux_head, self.rows)

    def save_periodic(self, ckpt_dir: Path, counters: dict, last: bool) -> None:
        if counters["round"] % self.args.save_freq == 0:
            self.save(ckpt_dir / "latest.pt", counters)

    def save_selected(self, path: Path, counters: dict) -> None:
        save_selected(path, self.policy, counters, self.args)

    def load_selected(self, path: Path) -> None:
        self.policy.load_state_dict(load_torch(path, FORMAT, "agents.dagger")["model"])

    def evaluate(self, args: Args, video_dir: Optional[Path] = None, first_seed: int = EVAL_SEED) -> dict:
        return final_evaluation(self.policy, args, self.device, video_dir, first_seed)

    def summary(self) -> dict:
        c = self.counters
        return dict(rounds=c["round"], train_episodes=c["episodes"], dataset=self.data.size, precision=self.precision)


def train(args: Args) -> dict:
    check_args(args)
    return loop.run(DAgger(args), Clock)


def main(args: Args) -> dict:
    check_budget(args)
    return run_evaluation_only(args) if args.evaluate else train(args)


if __name__ == "__main__":
    entry(Args, "agents.dagger", main)
