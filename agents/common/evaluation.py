"""What every trainer in ``agents/`` shares besides networks: observation layout, devices, RNG state,
atomic checkpoint writes, logging (TensorBoard, optional W&B / Comet) with the same metric names, and the
held-out evaluation every recipe is scored on (so the learning benchmark compares like with like)."""

from __future__ import annotations

import json
import os
import random
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import torch

# events the task reports per step in info; logged as per-episode rates ("did it happen")
EVENT_KEYS = ("success", "fail", "grasped", "dropped", "collided")
REWARD_TERM_PREFIX = "r_"
EVAL_SEED = 10_000_000
"""first seed of the held-out evaluation episodes; training seeds stay below it (see :func:`train_seed`)"""


def train_seed(seed: int, episode: int) -> int:
    """Seed of training episode ``episode`` of run ``seed``: disjoint from the evaluation seeds."""
    s = seed * 100_000 + episode
    if s >= EVAL_SEED:
        raise ValueError(f"training seed {s} (run seed {seed}, episode {episode}) would reach the held-out eval seeds")
    return s


def flatten_obs(obs) -> dict[str, torch.Tensor]:
    """Normalise both obs layouts to a dict with 'state' (and 'rgb'/'depth' for rgbd)."""
    if isinstance(obs, torch.Tensor):
        return {"state": obs}
    return obs


def obs_to(obs: dict, device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in obs.items()}


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def args_json(args) -> dict:
    return json.loads(json.dumps(asdict(args), default=str))


def atomic_save(obj: Any, path: Path) -> None:
    """torch.save to a temporary file, then rename: a crash never leaves a truncated checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def load_torch(path: Path, fmt: str, what: str) -> dict:
    """A checkpoint written by ``what`` in format ``fmt``, or an error that says why not."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise ValueError(f"checkpoint {path} is not a readable torch checkpoint: {e}") from e
    if not isinstance(ckpt, dict) or ckpt.get("format") != fmt:
        found = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt)
        raise ValueError(f"checkpoint {path} was not written by {what} (format {found})")
    return ckpt


def rng_state() -> dict:
    s = dict(python=random.getstate(), numpy=np.random.get_state(), torch=torch.get_rng_state())
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def set_rng_state(s: dict) -> None:
    random.setstate(s["python"])
    np.random.set_state(s["numpy"])
    torch.set_rng_state(s["torch"])
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])


class Logger:
    """TensorBoard always; W&B and Comet only when asked (imported lazily)."""

    def __init__(self, run_dir: Path, args):
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir))
        self.tb.add_text("args", json.dumps(json.loads(json.dumps(asdict(args), default=str)), indent=1))
        self.wandb = self.comet = None
        config = json.loads(json.dumps(asdict(args), default=str))
        if args.wandb:
            import wandb

            self.wandb = wandb.init(project=args.wandb_project, name=run_dir.name, config=config, dir=str(run_dir))
        if args.comet:
            import comet_ml

            self.comet = comet_ml.Experiment(project_name=args.comet_project)
            self.comet.set_name(run_dir.name)
            self.comet.log_parameters(config)

    def scalars(self, values: dict[str, float], step: int) -> None:
        for k, v in values.items():
            self.tb.add_scalar(k, v, step)
        if self.wandb is not None:
            self.wandb.log(values, step=step)
        if self.comet is not None:
            self.comet.log_metrics(values, step=step)

    def close(self) -> None:
        self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()
        if self.comet is not None:
            self.comet.end()


class EpisodeTracker:
    """Per-env running sums of the task's reward terms and 'did it ever happen' event flags,
    emitted per finished episode (rates of success, grasp, drop, collision; each term's return)."""

    def __init__(self, num_envs: int, device):
        self.n, self.device = num_envs, device
        self.sums: dict[str, torch.Tensor] = {}
        self.once: dict[str, torch.Tensor] = {}

    def update(self, step_info: dict, done: torch.Tensor) -> dict[str, list[float]]:
        done = done.to(self.device).bool()
        for k, v in step_info.items():
            if not isinstance(v, torch.Tensor) or v.shape[:1] != (self.n,) or v.dim() != 1:
                continue
            if k.startswith(REWARD_TERM_PREFIX):
                self.sums.setdefault(k, torch.zeros(self.n, device=self.device))
                self.sums[k] += v.to(self.device).float()
            elif k in EVENT_KEYS:
                self.once.setdefault(k, torch.zeros(self.n, dtype=torch.bool, device=self.device))
                self.once[k] |= v.to(self.device).bool()
        out: dict[str, list[float]] = defaultdict(list)
        if not done.any():
            return out
        ep = step_info.get("episode", {})
        for k in ("return", "episode_len"):
            if k in ep:
                out[k] += ep[k].to(self.device)[done].float().cpu().tolist()
        for k, v in self.once.items():
            out[f"{k}_rate"] += v[done].float().cpu().tolist()
            v[done] = False
        for k, v in self.sums.items():
            out[f"return_{k}"] += v[done].cpu().tolist()
            v[done] = 0
        return out


def evaluate_on_seeds(
    act: Callable[[dict[str, torch.Tensor]], torch.Tensor],
    env_id: str,
    obs: str,
    seeds: list[int],
    video_dir: Optional[Path] = None,
    progress: bool = False,
    wrappers: Sequence[Callable] = (),
    **env_kwargs,
) -> dict:
    """``act`` (batched obs dict -> actions) on one CPU env, one episode per seed, to the episode's end.

    Returns ``success_rate`` and the other event rates, mean return and length, each reward term's mean
    episode sum, and per-episode ``successes``. Every trainer's final score comes from here."""
    import gymnasium as gym
    from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper
    from mani_skill.utils.wrappers.record import RecordEpisode

    import maniskill_irb120  # noqa: F401

    kwargs = dict(obs_mode=obs, control_mode="pd_ee_delta_tool")
    kwargs.update(env_kwargs)
    if obs == "rgbd" or video_dir is not None:
        kwargs["render_mode"] = "rgb_array"
    else:
        kwargs.setdefault("render_backend", "none")
    env = gym.make(env_id, **kwargs)
    for w in wrappers:  # the policy's own action wrappers (e.g. WorldFrameToolAction), innermost first
        env = w(env)
    if obs == "rgbd":
        env = FlattenRGBDObservationWrapper(env)
    if video_dir is not None:
        env = RecordEpisode(env, str(video_dir), save_trajectory=False, video_fps=20, max_steps_per_video=None)
    stats: dict[str, list[float]] = defaultdict(list)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(seeds), unit="episode", desc="eval", dynamic_ncols=True)
    try:
        for seed in seeds:
            o, _ = env.reset(seed=int(seed))
            once: dict[str, bool] = {}
            sums: dict[str, float] = defaultdict(float)
            ret, steps, done = 0.0, 0, False
            while not done:
                with torch.no_grad():
                    a = act(flatten_obs(o))
                o, r, term, trunc, info = env.step(a)
                ret += float(r[0])
                steps += 1
                for k, v in info.items():
                    if k in EVENT_KEYS:
                        once[k] = once.get(k, False) or bool(v[0])
                    elif k.startswith(REWARD_TERM_PREFIX):
                        sums[k] += float(v[0])
                done = bool(term[0]) or bool(trunc[0])
            for k, v in once.items():
                stats[f"{k}_rate"].append(float(v))
            for k, v in sums.items():
                stats[f"return_{k}"].append(v)
            stats["return"].append(ret)
            stats["episode_len"].append(steps)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(success=f"{np.mean(stats['success_rate']):.2f}")
    finally:
        if bar is not None:
            bar.close()
        env.close()
    out = {k: float(np.mean(v)) for k, v in stats.items()}
    out["episodes"] = len(seeds)
    out["successes"] = [int(s) for s in stats["success_rate"]]
    return out


@dataclass
class RunArgs:
    """The flags agents.dagger and agents.sac share (where runs go, resuming, evaluating, loggers); each
    trainer's own Args extends it."""

    device: str = "auto"
    """torch device of the learner (auto: CUDA when available)"""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """the envs: gpu, ManiSkill's GPU-batched physx_cuda env (--num-envs in one process, its tensors copied to
    the host-side dataset each step); cpu, --num-envs worker processes (1: one env in this process); auto: gpu
    when CUDA is available"""
    exp_name: Optional[str] = None
    """run folder under --runs-dir (default: algorithm__env__obs__seed__time)"""
    runs_dir: Path = Path("runs")
    """TensorBoard logs, checkpoints and summary.json go to runs_dir/exp_name"""
    resume: Optional[Path] = None
    """continue a run: networks, optimisers, data, counters and RNG; the budget counts the time already spent"""
    evaluate: bool = False
    """only evaluate --checkpoint on the held-out seeds (videos + summary.json)"""
    checkpoint: Optional[Path] = None
    """the checkpoint --evaluate reads"""
    capture_video: bool = True
    """--evaluate: record an mp4 per episode"""
    progress: bool = True
    """a tqdm bar over the wall-clock budget"""
    wandb: bool = False
    """also log to Weights & Biases (imported only when set)"""
    comet: bool = False
    """also log to Comet, as the original report did (imported only when set)"""
    wandb_project: str = "maniskill_irb120"
    comet_project: str = "maniskill_irb120"
    env_kwargs: dict = field(default_factory=dict)
    """extra gym.make keyword arguments, e.g. domain randomisation ranges"""


def evaluate_checkpoint(
    args: RunArgs,
    load: Callable[[Path], tuple[Any, dict]],
    run: Callable[[Any, Optional[Path]], dict],
    must_match: Sequence[str] = ("obs", "action_frame"),
    adopt: Sequence[str] = ("obs_without",),
) -> dict:
    """``--evaluate``: ``load(path) -> (policy, checkpoint)``, refuse a checkpoint trained with other ``must_match``
    flags, take the ``adopt`` settings from it (what the policy was trained to see, not the command line's),
    ``run(policy, video_dir)``; writes ``eval/summary.json`` beside the run and prints it."""
    if args.checkpoint is None:
        raise ValueError("--evaluate needs --checkpoint PATH")
    policy, ckpt = load(args.checkpoint)
    for name in adopt:
        if hasattr(args, name):
            setattr(args, name, tuple(ckpt["args"].get(name) or ()))
    for name in must_match:
        trained = ckpt["args"].get(name)
        if trained != getattr(args, name):
            flag = "--" + name.replace("_", "-")
            raise ValueError(
                f"checkpoint {args.checkpoint} was trained with {flag} {trained}, not {getattr(args, name)}"
            )
    out_dir = Path(args.checkpoint).resolve().parent.parent / "eval"
    result = run(policy, out_dir / "videos" if args.capture_video else None)
    result["checkpoint"] = str(args.checkpoint)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result


def budget_bar(args: RunArgs, budget_s: float, spent_s: float, desc: str):
    """A tqdm bar over the wall-clock budget (None with --no-progress)."""
    if not args.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=int(budget_s), initial=int(spent_s), unit="s", desc=desc, dynamic_ncols=True)


def finish(result: dict, run_dir: Path) -> dict:
    """The run's ``summary.json`` and its last printed line (one JSON object)."""
    (run_dir / "summary.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result
