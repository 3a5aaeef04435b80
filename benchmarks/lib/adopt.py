"""Runs trained by hand (a trainer's own command, e.g. in an earlier session) joining a benchmark's row: each is
checked against the recipe from the arguments its TensorBoard log recorded, and only where and how it logged may
differ; a two-stage run is checked stage by stage, as the runner would have run it."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import tyro

from agents.common.logging import event_files
from agents.recipes import RECIPES
from benchmarks.lib.budget import budget_flags, budget_for, rest_of, steps_for
from benchmarks.lib.runner import RESULT_KEPT, RESULT_NEEDS, curve, finished_summary, joined, seeded

# where and how a run logged and kept its files, not what it learned: the only arguments an adopted run may differ
# in (``recipe``: the name a run was started with, whose flags are compared one by one like those given by hand)
ADOPT_FREE = ("seed", "exp_name", "runs_dir", "progress", "capture_video", "recipe", "keep_checkpoints")


BUDGET_ROUNDING = 0.01
"""minutes any adopted run's --budget-min may differ from the recipe's: the rounding of a budget typed to two
decimals, as the policies MANIFEST's commands give a second stage's (the total less the first stage's wall clock)"""


# what a --resume may change of a run's logged arguments besides those (the checkpoint it continued from)
RESUME_FREE = ("resume", "progress", "capture_video", "keep_checkpoints")


def logged_args(events: Path) -> tuple[dict, float]:
    """The arguments a trainer logged (agents.common.logging.Logger) and when its log was opened."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(events), size_guidance={"tensors": 0, "scalars": 1})
    acc.Reload()
    if "args/text_summary" not in acc.Tags()["tensors"]:
        raise ValueError(f"--adopt: {events} has no logged arguments")
    (text,) = acc.Tensors("args/text_summary")
    return json.loads(text.tensor_proto.string_val[0].decode()), text.wall_time


def adopted_pair(recipe: str, base_dir: Path, run_dir: Path, args) -> dict:
    """A two-stage run trained outside this script: the base stage checked against the base recipe at its share of
    the budget, the second against ``recipe`` with the rest of it and the base's checkpoint handed on, as
    ``train_run`` would have run them."""
    stage = RECIPES[recipe].for_task(args.env_id).base
    base_recipe, share, hand_on = stage.recipe, stage.share, f"--{stage.hand_on}"
    steps = steps_for(recipe, args)
    if steps is not None:
        total, base_steps = steps
        base = adopted_run(base_recipe, base_dir, args, stage_budget=args.max_minutes, stage_steps=base_steps)
        rest, rest_steps = (
            rest_of(args.max_minutes, base["wall_clock_s"] / 60),
            round(rest_of(total, base["env_steps"])),
        )
    else:
        budget = budget_for(recipe, args)
        base = adopted_run(base_recipe, base_dir, args, stage_budget=share * budget)
        rest, rest_steps = rest_of(budget, base["wall_clock_s"] / 60), None
    extra = [hand_on, base["checkpoint"]]
    tuned = adopted_run(recipe, run_dir, args, stage_budget=rest, extra=extra, stage_steps=rest_steps)
    return dict(joined(base, tuned), adopted_from=f"{base_dir} + {run_dir}")


def adopted_run(
    recipe: str,
    run_dir: Path,
    args,
    stage_budget: Optional[float] = None,
    extra: list[str] = (),
    stage_steps: Optional[int] = None,
) -> dict:
    """A finished run of ``recipe`` trained outside this script, checked against the recipe and read as
    ``run_trainer`` reads its own (its summary.json is the result line; its curve's clock starts when its log was
    opened, seconds after the process). ``stage_budget``, ``stage_steps`` and ``extra``: one stage of a two-stage
    recipe (:func:`adopted_pair`)."""
    import importlib

    r = RECIPES[recipe].for_task(args.env_id)
    module, flags = r.trainer, [*r.argv(), *extra]
    if r.base is not None and not extra:
        raise ValueError(f"--adopt: {recipe} trains in two stages; name each run's first stage with --adopt-base")
    summary, events = finished_summary(run_dir), event_files(run_dir)
    if summary is None:
        raise FileNotFoundError(f"--adopt: {run_dir} has no summary.json (the run did not finish)")
    if not events:
        raise ValueError(f"--adopt: {run_dir} has no TensorBoard log")
    trainer = importlib.import_module(module)
    # a field a run's log predates was the field's default then (as --resume reads an older checkpoint)
    defaults = json.loads(json.dumps(asdict(trainer.Args()), default=str))
    logged, opened = logged_args(events[0])
    logged = {**defaults, **logged}
    for later in events[1:]:  # a resumed run: each session logged the arguments it continued with
        theirs = {**defaults, **logged_args(later)[0]}
        differ = sorted(k for k in set(logged) | set(theirs) if k not in RESUME_FREE and logged.get(k) != theirs.get(k))
        if differ:
            shown = ", ".join(f"{k}={theirs.get(k)!r} (first: {logged.get(k)!r})" for k in differ)
            raise ValueError(f"--adopt: {later} continued {run_dir} with other arguments: {shown}")
    if stage_budget is None and stage_steps is None:  # a single-stage run: the recipe's budget
        steps = steps_for(recipe, args)
        stage_steps = None if steps is None else steps[0]
        stage_budget = budget_for(recipe, args) if steps is None else args.max_minutes
    seed = logged.get("seed")
    argv = [
        *seeded(flags, seed),
        "--env-id",
        args.env_id,
        "--seed",
        str(seed),
        *budget_flags(stage_budget, stage_steps),
    ]
    argv += ["--eval-episodes", str(args.eval_episodes)]
    trainer_args = tyro.cli(trainer.Args, args=argv)
    if hasattr(trainer, "resolved"):  # defaults a trainer fills in from other flags, logged filled in
        trainer_args = trainer.resolved(trainer_args)
    expected = json.loads(json.dumps(asdict(trainer_args), default=str))
    differ = {k: (logged.get(k), v) for k, v in expected.items() if k not in ADOPT_FREE and logged.get(k) != v}
    typed = differ.get("budget_min")
    if typed and None not in typed and abs(float(typed[0]) - float(typed[1])) <= BUDGET_ROUNDING + 1e-9:
        del differ["budget_min"]  # a second stage's budget typed to two decimals: its rounding, not another budget
    if differ:
        shown = ", ".join(f"{k}={a!r} (the recipe's: {b!r})" for k, (a, b) in sorted(differ.items()))
        raise ValueError(f"--adopt: {run_dir} was not trained by the {recipe} recipe: {shown}")
    result = json.loads(summary.read_text())
    missing = RESULT_NEEDS - set(result)
    if missing:
        raise ValueError(f"--adopt: {summary} lacks {sorted(missing)}")
    out = {k: result[k] for k in RESULT_KEPT if k in result}
    out.update(
        seed=logged["seed"],
        command=" ".join(["-m", module, *argv]),
        adopted_from=str(run_dir),
        benchmark_command=f"python -m {module} {' '.join(argv)}",
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(opened)),
        curve=curve(run_dir),
    )
    return out
