"""The pieces of a run every trainer's loop (agents.common.loop) is made of: its folder and resume
(:func:`open_run`), the budget clock (:class:`Clock`) and when the budget stops training (:class:`Budget`: env steps,
``--total-env-steps``, with ``--max-minutes`` a guard; both span a ``--resume``), the checkpoint's common part and its
restore, the last save however training ends, and the held-out evaluation that ends the run. See docs/training.md."""

from __future__ import annotations

import random
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from agents.common.args import RunArgs
from agents.common.checkpoints import FORMAT_VERSION, args_json, rng_state, set_rng_state, signature_mismatch
from agents.common.envs import action_wrappers
from agents.common.evaluation import EVAL_SEED, evaluate_on_seeds
from agents.common.logging import budget_bar, finish
from maniskill_irb120.wrappers import observation_setup


def open_run(args: RunArgs, prefix: str, read: Callable[[Path], dict]) -> tuple[Optional[dict], Path]:
    """(the checkpoint ``--resume`` names, read by ``read``, or None; the run's folder), with python, numpy and torch
    seeded by ``--seed`` (a resumed run then restores its checkpoint's RNG: :func:`restore`). A resumed run continues
    in its checkpoint's folder; a new one is ``runs_dir/exp_name``, by default ``prefix`` + env__obs__seed__time."""
    saved = read(args.resume) if args.resume is not None else None
    if saved is not None:
        run_dir = Path(args.resume).resolve().parent.parent
    else:
        run_dir = args.runs_dir / (
            args.exp_name or f"{prefix}{args.env_id}__{args.obs}__{args.seed}__{int(time.time())}"
        )
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    return saved, run_dir


class Clock:
    """Seconds of training on the run's budget: ``before`` (trained before a ``--resume``: its checkpoint's
    ``counters["wall_s"]``) plus this process's since the clock started."""

    def __init__(self, before: float = 0.0):
        self.before = before
        self.t0 = time.perf_counter()

    def __call__(self) -> float:
        return self.before + self.session()

    def session(self) -> float:
        """Seconds since this process's clock started (this session's share of the run)."""
        return time.perf_counter() - self.t0


def checkpoint(fmt: str, args: RunArgs, counters: dict, **state) -> dict:
    """A checkpoint's contents: the trainer's format tag and the layout's ``format_version``, counters (with
    ``wall_s``, the budget clock), the RNG and the run's flags, around ``state`` (networks, optimisers, data
    manifests, the policy section)."""
    return dict(
        format=fmt, format_version=FORMAT_VERSION, counters=counters, rng=rng_state(), args=args_json(args), **state
    )


def restore(saved: dict, clock: Optional[Clock] = None) -> dict:
    """The counters of a checkpoint being resumed, with its RNG state restored; given the run's ``clock`` (started
    before the checkpoint was read), the seconds trained before the resume go on it (``counters["wall_s"]``)."""
    set_rng_state(saved["rng"])
    counters = dict(saved["counters"])
    if clock is not None:
        clock.before = counters["wall_s"]
    return counters


def check_resume_signature(saved: dict, signature: dict, resume: Path, args=None) -> None:
    """The checkpoint ``--resume`` names holds networks of this run's shapes (``signature``: the model's
    ``signature()``, what its observation and flags make of it), else a UsageError naming what differs and the flag
    that fixes it (``args``: the run's, whose fields are its flags): loading the weights would fail deep in torch, or
    worse, fit and mean something else."""
    if saved["signature"] != signature:
        raise signature_mismatch(f"--resume {resume}", saved["signature"], signature, args)


def env_step_budget(args: RunArgs) -> Optional[int]:
    """The run's budget in env steps: ``--total-env-steps``, or None (the wall guard alone)."""
    return args.total_env_steps


def wall_guard_s(args: RunArgs, default_min: Optional[float] = None) -> Optional[float]:
    """The wall-clock guard in seconds: ``--max-minutes``, else ``--budget-min`` (its old name), else
    ``default_min`` for a run with no env-step budget (DAgger's and SAC's, which have no other end), else None: a
    run given env steps is not stopped by a clock it did not ask for."""
    minutes = args.max_minutes if args.max_minutes is not None else args.budget_min
    if minutes is not None:
        return 60 * minutes
    return 60 * default_min if default_min is not None and env_step_budget(args) is None else None


class Budget:
    """When a trainer stops: a step (a PPO iteration, a SAC env step with its updates, a DAgger round) starts only
    while fewer than ``total_env_steps`` env steps are done (``counters[steps_key]``, so a ``--resume`` goes on
    counting) and the wall guard ``budget_s`` allows it. The guard lets a step start only while the longest step
    so far, plus the validation that may follow it, still ends within it: a stage of a staged recipe, whose minutes
    count towards a target, would otherwise overrun. The longest, not the last: when unsure, stop early. The
    estimates live in ``counters`` (``step_s``, ``validation_s``) and so in every checkpoint. Every time is read on
    ``clock``, the budget's own. None for either: no limit of that kind."""

    def __init__(
        self,
        budget_s: Optional[float],
        clock: Clock,
        counters: dict,
        validates: bool,
        total_env_steps: Optional[int] = None,
        steps_key: str = "env_steps",
    ):
        self.budget_s, self.clock, self.counters, self.validates = budget_s, clock, counters, validates
        self.total_env_steps, self.steps_key = total_env_steps, steps_key
        self._t0, self._validating = clock(), 0.0

    def env_steps(self) -> int:
        return self.counters[self.steps_key]

    def steps_left(self) -> bool:
        return self.total_env_steps is None or self.env_steps() < self.total_env_steps

    def reserve_s(self) -> float:
        """Seconds kept for the validation that ends the run (0 for a run that validates nothing)."""
        return self.counters.get("validation_s", 0.0) if self.validates else 0.0

    def time_fits(self) -> bool:
        if self.budget_s is None:
            return True
        return self.clock() + self.counters.get("step_s", 0.0) + self.reserve_s() <= self.budget_s

    def next_step_fits(self) -> bool:
        return self.steps_left() and self.time_fits()

    def out_of_time(self) -> bool:
        """Within a step (DAgger's updates): only the final validation's time is left."""
        return self.budget_s is not None and self.clock() + self.reserve_s() > self.budget_s

    def start_step(self) -> None:
        self._t0, self._validating = self.clock(), 0.0

    def end_step(self) -> None:
        """The step's seconds since :meth:`start_step`, less its validations (they have their own estimate)."""
        took = self.clock() - self._t0 - self._validating
        self.counters["step_s"] = max(self.counters.get("step_s", 0.0), took)

    @contextmanager
    def validation(self) -> Iterator[None]:
        t = self.clock()
        try:
            yield
        finally:
            took = self.clock() - t
            self._validating += took
            self.counters["validation_s"] = max(self.counters.get("validation_s", 0.0), took)

    def stopped_early(self) -> bool:
        """The guard ended training before its env-step budget (False for a run without one)."""
        return self.total_env_steps is not None and self.env_steps() < self.total_env_steps

    def report(self) -> dict:
        """What ``summary.json`` records of the budget, and the line a run the guard stopped prints."""
        guard = None if self.budget_s is None else self.budget_s / 60
        early = self.stopped_early()
        if early:
            print(f"stopped early at {self.env_steps()} env steps (of {self.total_env_steps})", flush=True)
        return dict(total_env_steps=self.total_env_steps, max_minutes=guard, stopped_early=early)

    def bar(self, args: RunArgs, desc: str):
        """A tqdm bar over the env-step budget, else over the guard's seconds (None with --no-progress)."""
        if self.total_env_steps is not None:
            return budget_bar(args, self.total_env_steps, self.env_steps(), desc, unit="step")
        return budget_bar(args, self.budget_s, self.clock(), desc) if self.budget_s is not None else None

    def advance(self, bar) -> None:
        if bar is not None:
            done = self.env_steps() if self.total_env_steps is not None else self.clock()
            bar.n = min(int(done), int(bar.total))


def close_and_save(bar, envs, counters: dict, clock: Clock, save: Callable[[dict], object]) -> None:
    """The end of training however it comes (the budget, an exception, Ctrl-C: call it in a ``finally``): the
    progress bar (or None) closed, the training clock read into ``counters["wall_s"]``, ``save(counters)`` writing
    the last checkpoint, so that ``--resume`` continues from where it stopped, and then the envs closed (even if the
    save raised). The checkpoint is written first because a vector env interrupted mid-step may take its close
    timeout to shut its workers down, or, for an env without one, not return at all. Closing while a step is pending
    is the expected way out of a Ctrl-C or SIGTERM that lands mid-step, so gymnasium's warning about it (which would
    break the interrupted run's one-line message) is silenced; any other warning still shows."""
    try:
        if bar is not None:
            bar.close()
        counters["wall_s"] = clock()
        save(counters)
    finally:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=PENDING_CLOSE_WARNING)
            envs.close()


PENDING_CLOSE_WARNING = r".*Calling `close` while waiting for a pending call"
"""gymnasium's ``AsyncVectorEnv.close`` warning when a step is still in flight (it then waits for that step)"""


def held_out_evaluation(
    act: Callable[[dict], torch.Tensor],
    args: RunArgs,
    video_dir: Optional[Path] = None,
    first_seed: int = EVAL_SEED,
    **env_kwargs,
) -> dict:
    """``act`` (batched obs -> actions) on ``args.eval_episodes`` seeds from ``first_seed`` (the held-out ones by
    default), in the run's task, observation (hiding ``obs_without`` for a trainer that has it) and action frame,
    with ``env_kwargs`` over the run's ``--env-kwargs``: how every trainer's policy is scored."""
    seeds = list(range(first_seed, first_seed + args.eval_episodes))
    wrappers = action_wrappers(args.action_frame)
    kwargs = dict(args.env_kwargs)
    if hasattr(args, "obs_without"):
        obs_mode, obs_wrappers = observation_setup(args.obs, args.obs_without)
        wrappers = [*obs_wrappers, *wrappers]
        kwargs["obs_mode"] = obs_mode
    kwargs.update(env_kwargs)
    return evaluate_on_seeds(
        act, args.env_id, args.obs, seeds, video_dir=video_dir, progress=args.progress, wrappers=wrappers, **kwargs
    )


def evaluate_and_finish(evaluate: Callable[[], dict], logger, counters: dict, run_dir: Path, **extra) -> dict:
    """The run's end: ``evaluate()`` (the held-out episodes) logged as ``eval/``, then ``summary.json`` and the
    printed JSON line with the counters' env steps and training wall clock, the evaluation's own time and ``extra``."""
    t_eval = time.perf_counter()
    result = evaluate()
    logger.scalars({f"eval/{k}": v for k, v in result.items() if isinstance(v, float)}, counters["env_steps"])
    logger.close()
    result.update(
        env_steps=counters["env_steps"],
        wall_clock_s=counters["wall_s"],
        eval_wall_s=time.perf_counter() - t_eval,
        **extra,
        run_dir=str(run_dir),
    )
    return finish(result, run_dir)
