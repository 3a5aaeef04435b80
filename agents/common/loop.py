"""The one training loop: a trainer gives its algorithm (:class:`Algorithm`: build, one step of collecting and
updating, save, the policy to score) and :func:`run` owns the rest, the same for every trainer: the run's folder and
resume, the budget, checkpoint selection on validation seeds, periodic and final saves, the held-out evaluation and
``summary.json``. See docs/training.md."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

from agents.common.args import RunArgs
from agents.common.evaluation import EVAL_SEED, VALIDATION_SEED, next_curve_share
from agents.common.logging import Logger
from agents.common.run import (
    Budget,
    Clock,
    close_and_save,
    env_step_budget,
    evaluate_and_finish,
    open_run,
    restore,
    wall_guard_s,
)


class Algorithm:
    """A trainer's own part of a run. ``counters`` (``env_steps`` and the trainer's own) is the loop's and goes into
    every checkpoint; :meth:`step` moves it. Override what the trainer does; the defaults are what most need."""

    name = "train"
    """the progress bar's label"""
    prefix = ""
    """the run folder's prefix (``sac__``)"""
    default_minutes: Optional[float] = None
    """the wall guard of a run given neither --total-env-steps nor --max-minutes (None: such a run is refused)"""
    step_key = "env_steps"
    """the counter :attr:`RunArgs.select_freq` counts (a PPO iteration, a DAgger round)"""

    def __init__(self, args: RunArgs):
        self.args = args
        self.counters: dict = dict(env_steps=0)

    def read(self, path: Path) -> dict:
        """The checkpoint ``--resume`` names (format-checked and migrated)."""
        raise NotImplementedError

    def build(self, saved: Optional[dict]):
        """The training envs (returned: the loop closes them), networks and optimisers, ``saved``'s state loaded."""
        raise NotImplementedError

    def start(self) -> None:
        """After the counters are restored, before the first step: reset the envs (and any pre-training)."""

    def step(self, budget: Budget) -> dict:
        """One step of training (collect, then update), the counters moved; the scalars to log ({}: none now)."""
        raise NotImplementedError

    def postfix(self, scalars: dict) -> dict:
        """What the progress bar shows after a step that logged ``scalars``."""
        return {}

    def estimates(self) -> bool:
        """Whether the step just taken is an estimate of the next one's time (:meth:`Budget.end_step`)."""
        return True

    def must_step(self) -> bool:
        """A step that runs whatever the budget says (DAgger's round 0: no policy exists before it)."""
        return False

    def save(self, path: Path, counters: dict) -> None:
        """The checkpoint ``--resume`` continues (``latest.pt``)."""
        raise NotImplementedError

    def save_periodic(self, ckpt_dir: Path, counters: dict, last: bool) -> None:
        """The checkpoints written during training (none by default: ``latest.pt`` is written at the end)."""

    def save_selected(self, path: Path, counters: dict) -> None:
        """``best.pt``, the policy checkpoint selection keeps."""
        self.save(path, counters)

    def load_selected(self, path: Path) -> None:
        """The weights of ``best.pt`` into the policy the held-out episodes score."""
        raise NotImplementedError

    def evaluate(self, args: RunArgs, video_dir: Optional[Path] = None, first_seed: int = EVAL_SEED) -> dict:
        """The policy on ``args.eval_episodes`` seeds from ``first_seed`` (agents.common.run.held_out_evaluation)."""
        raise NotImplementedError

    def selected(self, best: dict) -> dict:
        """What ``summary.json["selected"]`` says of the kept checkpoint (its counters at the time)."""
        return {k: v for k, v in best.items() if k != "score"}

    def summary(self) -> dict:
        """The trainer's own keys of ``summary.json``."""
        return {}

    def close(self) -> None:
        """Anything besides the training envs (PPO's periodic evaluation envs)."""


def run(algo: Algorithm, clock_type: type[Clock] = Clock) -> dict:
    """Trains ``algo`` under its ``args`` and returns the run's last word (also ``summary.json``). The budget's clock
    (a ``clock_type``) starts once the envs are built and counts the seconds trained before a ``--resume``."""
    args = algo.args
    saved, run_dir = open_run(args, algo.prefix, algo.read)
    algo.run_dir = run_dir
    envs = algo.build(saved)
    counters = algo.counters
    if saved is not None:
        counters = algo.counters = restore(saved)
    clock = clock_type(counters.get("wall_s", 0.0))
    logger = Logger(run_dir, args, clock)
    ckpt_dir = run_dir / "checkpoints"
    budget = Budget(
        wall_guard_s(args, algo.default_minutes),
        clock,
        counters,
        args.select_episodes > 0,
        total_env_steps=env_step_budget(args),
    )
    bar = budget.bar(args, algo.name)
    algo.logger = logger
    validated = counters.get(algo.step_key, 0) % args.select_freq == 0  # (nothing to validate before a step)
    try:
        algo.start()
        while True:
            if not algo.must_step() and not budget.next_step_fits():
                if args.select_episodes and budget.steps_left() and not validated:  # the clock stopped it
                    select(algo, counters, clock, budget, ckpt_dir)
                break
            budget.start_step()
            before = counters.get(algo.step_key, 0)
            scalars = algo.step(budget)
            if scalars:
                logger.scalars(scalars, counters["env_steps"])
                if bar is not None:
                    bar.set_postfix(**algo.postfix(scalars))
            budget.advance(bar)
            last = not budget.steps_left()
            now = counters.get(algo.step_key, 0)
            validated = bool(args.select_episodes) and (now // args.select_freq > before // args.select_freq or last)
            if validated:  # every --select-freq steps and after the last
                select(algo, counters, clock, budget, ckpt_dir)
            if curve_point_due(args, counters) and not last:  # the end's point is the final evaluation
                held_out_point(algo, counters, clock)
            counters["wall_s"] = clock()
            algo.save_periodic(ckpt_dir, counters, last)
            if algo.estimates():
                budget.end_step()
    finally:
        try:
            close_and_save(bar, envs, counters, clock, lambda c: algo.save(ckpt_dir / "latest.pt", c))
        finally:
            algo.close()
    extra = dict(algo.summary(), **scored_checkpoint(algo, ckpt_dir))
    if args.curve_points:
        extra["held_out_curve"] = counters.get("held_out_curve", [])
    if args.select_episodes:
        extra["selection_checks"] = counters.get("selection_checks", [])
    evaluate = (lambda: algo.evaluate(args)) if args.eval_episodes > 0 else dict  # 0: no held-out evaluation
    return evaluate_and_finish(evaluate, logger, counters, run_dir, **extra, **budget.report())


def curve_point_due(args: RunArgs, counters: dict) -> bool:
    """A held-out curve point is due (``--curve-points``): the env steps have crossed the next share of the budget
    (:func:`~agents.common.evaluation.next_curve_share`)."""
    if not args.curve_points or args.total_env_steps is None:
        return False
    share = next_curve_share(args.curve_points, args.total_env_steps, counters.get("held_out_curve", []))
    return share is not None and counters["env_steps"] >= share * args.total_env_steps


def held_out_point(algo: Algorithm, counters: dict, clock: Clock) -> None:
    """The policy as it is now on ``--curve-episodes`` held-out seeds (EVAL_SEED onwards, the final evaluation's
    first), kept in ``counters["held_out_curve"]`` as [env steps, training minutes, success rate, per-episode
    successes, evaluation seconds] and logged as ``eval/held_out_success``; its time is left out of the budget
    clock (it is not training), as benchmarks/algorithms.py leaves a library cell's out."""
    from dataclasses import replace

    args = algo.args
    started = time.perf_counter()
    r = algo.evaluate(replace(args, eval_episodes=args.curve_episodes, progress=False), None, EVAL_SEED)
    took = time.perf_counter() - started
    clock.t0 += took  # the budget clock skips the evaluation
    steps = counters["env_steps"]
    counters.setdefault("held_out_curve", []).append([steps, clock() / 60, r["success_rate"], r["successes"], took])
    algo.logger.scalars({"eval/held_out_success": r["success_rate"]}, steps)
    print(f"[{algo.name}] held out at {steps:,} env steps: success {r['success_rate']:.2f} of "
          f"{len(r['successes'])} ({took:.0f} s)", flush=True)  # fmt: skip


def scored_checkpoint(algo: Algorithm, ckpt_dir: Path) -> dict:
    """What the held-out episodes score, loaded into ``algo``: with selection, the selected weights (``best.pt``;
    ``--resume`` continues from the last ones, ``latest.pt``), else the last; the summary's keys saying so."""
    best = algo.counters.get("best")
    if not (algo.args.select_episodes and best is not None):
        return dict(checkpoint=str(ckpt_dir / "latest.pt"))
    algo.load_selected(ckpt_dir / "best.pt")
    selected = dict(algo.selected(best), validation_success_rate=best["score"][0])
    selected["validation_episodes"] = algo.args.select_episodes
    return dict(checkpoint=str(ckpt_dir / "best.pt"), last_checkpoint=str(ckpt_dir / "latest.pt"), selected=selected)


def select(algo: Algorithm, counters: dict, clock: Clock, budget: Budget, ckpt_dir: Path) -> None:
    """Checkpoint selection: the policy on ``--select-episodes`` validation seeds, kept as ``best.pt`` when it beats
    the best so far (success rate, then mean return); its time is the budget's validation estimate. Each check is
    kept in ``counters["selection_checks"]`` as [env steps, success rate, mean return] (summary.json's)."""
    from dataclasses import replace

    args = algo.args
    with budget.validation():
        v = algo.evaluate(replace(args, eval_episodes=args.select_episodes, progress=False), None, VALIDATION_SEED)
        algo.logger.scalars({f"select/{k}": v[k] for k in ("success_rate", "return") if k in v}, counters["env_steps"])
        score = [v.get("success_rate", 0.0), v["return"]]
        # every check, kept across --resume, so that two runs of one seed can be compared check by check
        counters.setdefault("selection_checks", []).append([counters["env_steps"], *score])
        best = counters.get("best")
        if best is None or score > best["score"]:
            counters["best"] = {"score": score, algo.step_key: counters.get(algo.step_key, 0)}
            counters["best"]["env_steps"] = counters["env_steps"]
            counters["wall_s"] = clock()
            algo.save_selected(ckpt_dir / "best.pt", counters)
