"""The held-out evaluation every recipe is scored on (so the learning benchmark compares like with like): the
seeds, per-episode task metrics, the one-env episode loop and a trainer's ``--evaluate``. See docs/training.md."""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from agents.common.args import RunArgs
from agents.common.envs import flatten_obs

# events the task reports per step in info; logged as per-episode rates ("did it happen"). "lifted" (GraspLift) and
# "stacked" (StackCube) are the stage between the grasp and success, so a curve that grasps but never succeeds says
# which stage it stalls at
EVENT_KEYS = ("success", "fail", "grasped", "lifted", "stacked", "dropped", "collided")
REWARD_TERM_PREFIX = "r_"
EVAL_SEED = 10_000_000
"""first seed of the held-out evaluation episodes; training seeds stay below it (see :func:`train_seed`)"""
VALIDATION_SEED = 20_000_000
"""first seed of the episodes a trainer selects its checkpoint on: apart from training (below EVAL_SEED) and from
the held-out seeds, so the score of the selected checkpoint is not the score it was selected by"""


def curve_fractions(points: int) -> list[float]:
    """The shares of an env-step budget where a held-out curve point is taken while training: every ``1/points`` and
    a quarter (tables read 25 %, 50 % and 100 %), not the end, which the final evaluation is."""
    if points < 2:
        return []
    return sorted({k / points for k in range(1, points)} | {0.25})


def next_curve_share(points: int, total_env_steps: int, taken: list) -> Optional[float]:
    """The next of :func:`curve_fractions` of ``total_env_steps`` past the last point taken (``taken``: the points so
    far, each row starting with its env steps); None when none is left. A step that crossed several shares took one
    point for them all."""
    last_steps = taken[-1][0] if taken else -1
    left = [f for f in curve_fractions(points) if f * total_env_steps > last_steps]
    return left[0] if left else None


def new_eval_dir(run_dir: Path) -> Path:
    """``run_dir/eval`` for a run's first ``--evaluate``, then ``eval-2``, ``eval-3``...: a second evaluation of the
    same run (another checkpoint, more episodes) must not overwrite the first one's summary and videos."""
    out, k = run_dir / "eval", 1
    while out.exists():
        k += 1
        out = run_dir / f"eval-{k}"
    return out


def train_seed(seed: int, episode: int) -> int:
    """Seed of training episode ``episode`` of run ``seed``: disjoint from the evaluation seeds."""
    s = seed * 100_000 + episode
    if s >= EVAL_SEED:
        raise ValueError(f"training seed {s} (run seed {seed}, episode {episode}) would reach the held-out eval seeds")
    return s


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


def evaluate_checkpoint(
    args: RunArgs,
    load: Callable[[Path], tuple[Any, dict]],
    run: Callable[[Any, Optional[Path]], dict],
    must_match: Sequence[str] = ("obs", "action_frame"),
    adopt: Sequence[str] = ("obs_without",),
) -> dict:
    """``--evaluate``: ``load(path) -> (policy, checkpoint)``, refuse a checkpoint trained with other ``must_match``
    flags, take the ``adopt`` settings from it (what the policy was trained to see, not the command line's),
    ``run(policy, video_dir)``; writes ``eval/summary.json`` beside the run (``eval-2/``... when taken: see
    :func:`new_eval_dir`) and prints it."""
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
    # beside the run; an exported policy has no run (it may sit in the repository): --runs-dir/--exp-name
    run_dir = Path(args.checkpoint).resolve().parent.parent
    if ckpt.get("exported"):
        run_dir = Path(args.runs_dir) / (args.exp_name or Path(args.checkpoint).stem)
    out_dir = new_eval_dir(run_dir)
    result = run(policy, out_dir / "videos" if args.capture_video else None)
    result["checkpoint"] = str(args.checkpoint)
    result["eval_dir"] = str(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result
