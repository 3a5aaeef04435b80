"""Does it learn? Every recipe x seeds under one budget, scored on held-out seeds, with intervals.

Each recipe is a trainer CLI in ``agents/`` run as a subprocess with its budget, ``--seed`` and
``--eval-episodes``; the last line it prints is its JSON result (``success_rate``, ``successes`` per
episode, ``env_steps``, ``wall_clock_s``), and its TensorBoard log gives the curve (training-episode success
against env steps and the trainer's budget clock, across every session of a resumed run). References measured in
the same run on the same held-out seeds: uniform random actions and the scripted expert.

Intervals: the mean success over seeds with a 95 % percentile bootstrap that resamples seeds and then the
episodes within each (a two-level stratified bootstrap, the method of ``rliable``; written here in numpy
because rliable 1.2 does not import beside our stack: it needs ``arch < 8``, and arch 7.2 fails at import with
the pandas 3.1 installed here, ``TypeError: deprecate_kwarg()``; rliable's bootstrap also
resamples runs only, which with 1-3 seeds ignores the 100 episodes' own sampling noise), and the interquartile
mean of the seeds' success rates
(rliable's aggregate over runs; over single episodes, each 0 or 1, it would only say whether success is above
75 % or below 25 %).

    python -m benchmarks.learning                                  # every recipe x 3 seeds (hours: see below)
    python -m benchmarks.learning --recipes dagger-state --seeds 1 2 3
    python -m benchmarks.learning --recipes ppo-state --env-step-budgets --max-minutes 60   # the committed env steps
    python -m benchmarks.learning --quick --out-dir /tmp/lq        # CI smoke run (~3 min, no targets)
    python -m benchmarks.learning --recipes dagger-rgbd-bf16 --seeds --adopt runs/s1 runs/s2 --merge
                                 # runs trained by the trainer's own command join the row, once checked
    python -m benchmarks.learning --env-id TableClearing-IRB120-v1 --recipes teacher-student-rgbd-sel --merge \
        --stop-after-min 140     # runs longer than a session: run the same command again until none is unfinished

Budgets in env steps (``--total-env-steps`` for every run, or ``--env-step-budgets``: each recipe's committed runs'
env steps on the task, ``agents.recipes.ENV_STEP_BUDGETS``), with ``--max-minutes`` as a guard, hold a row to the same
training whatever the host's speed, which moved several-fold between days; the reference speed before and after each
run is recorded beside it (``reference_sps``). Without them, the minutes the committed rows were held to, as then
(the issue's targets): dagger-state, dagger-rgbd-bf16 and ppo-finetune-state ``--budget-min`` (60; the
last trains its DAgger base for half of it, then fine-tunes with PPO for the rest), ppo-state and
sac-scratch-state ``--rl-budget-min`` (RL_BUDGET_MIN of the task), dagger-rgbd and sac-state
``--long-budget-min`` (120); the final evaluation is extra. A recipe's flags are the same on every task but for
its task changes (GraspLift's ppo-state adds ``--logstd state``), and a two-stage recipe's base gets its share of the
budget from its ``Base`` but where a task gives its own. The recipes and their budgets live
in ``agents/recipes.py``, which the trainers' ``--recipe NAME`` reads too: a run here and a trainer
started by hand with the same recipe get the same flags. With ``--stop-after-min`` the run in progress is
interrupted at its checkpoint when the minutes are up, and the same command continues it; Ctrl-C or SIGTERM does the
same at once (``benchmarks.lib.runner.run_until``), and the exit status is then 130. ``--update-results``
rewrites the Learning section of benchmarks/RESULTS.md; ``--render-only`` redraws it and the plot from the task's
committed learning.json, training nothing.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from agents.common import EVAL_SEED, evaluate_on_seeds
from agents.recipes import (
    DEFAULT_ENV,
    LONG_BUDGET_MIN,
    RECIPES,
    RL_BUDGET_MIN,
    SHORT_BUDGET_MIN,
    VISION_BUDGET_MIN,
)
from benchmarks.lib.adopt import adopted_pair, adopted_run
from benchmarks.lib.budget import steps_for
from benchmarks.lib.cli import entry
from benchmarks.lib.machine import REFERENCE_STEPS, reference_speed
from benchmarks.lib.report import replace_section, smoothed
from benchmarks.lib.runner import ROOT, Interrupted, finished_summary, run_name, train_run
from benchmarks.lib.stats import bootstrap_ci, iqm

REFERENCES = ("random", "expert")
QUICK_RECIPES = ("dagger-state", "ppo-state", "ppo-finetune-state", "sac-scratch-state")


@dataclass
class Args:
    recipes: list[str] = field(default_factory=lambda: list(RECIPES))
    """which of dagger-state, dagger-rgbd, dagger-rgbd-bf16, dagger-rgbd-bf16-dr, sac-state, ppo-state,
    sac-scratch-state, ppo-finetune-state, teacher-student-rgbd, teacher-student-rgbd-sel, ppo-rgbd-dense, ppo-rgbd
    to train (random and the expert always run)"""
    seeds: list[int] = field(default_factory=lambda: [1, 2, 3])
    budget_min: float = SHORT_BUDGET_MIN
    """wall-clock minutes per run of dagger-state, dagger-rgbd-bf16 and ppo-finetune-state (its base and
    fine-tuning together; data collection and training)"""
    long_budget_min: float = LONG_BUDGET_MIN
    """wall-clock minutes per run of dagger-rgbd and sac-state"""
    eval_episodes: int = 100
    """held-out episodes per run and per reference (seeds agents.common.EVAL_SEED onwards)"""
    rl_budget_min: Optional[float] = None
    """wall-clock minutes per run of ppo-state and sac-scratch-state (default: RL_BUDGET_MIN of the task)"""
    vision_budget_min: Optional[float] = None
    """wall-clock minutes per run of teacher-student-rgbd and -sel (both stages), ppo-rgbd-dense and ppo-rgbd
    (default: VISION_BUDGET_MIN of the task)"""
    total_env_steps: Optional[int] = None
    """the budget of every run in env steps instead of minutes (a two-stage recipe's both stages, its first getting
    the share its committed runs did, else BASES' share)"""
    env_step_budgets: bool = False
    """each recipe's budget in env steps: the env steps its committed runs on the task did (recipes.ENV_STEP_BUDGETS),
    so the row repeats the committed one whatever this machine's speed; a recipe with none there is refused"""
    max_minutes: Optional[float] = None
    """with an env-step budget: a wall-clock guard per run (a two-stage run's second stage gets what its first left);
    a run it stops before its env steps says so in its result ("stopped_early")"""
    env_id: str = DEFAULT_ENV
    """the task; each has its own report (--out-dir) and its own Learning section in RESULTS.md"""
    out_dir: Optional[Path] = None
    """default benchmarks/results/learning, and a subfolder named after the task for the others"""
    merge: bool = False
    """keep the rows of recipes this run does not train from the existing learning.json, and a retrained recipe's
    runs of seeds this run does not train (each with the command and date it came from): a 2-core machine runs
    the recipes and seeds one session at a time"""
    adopt: list[Path] = field(default_factory=list)
    """run folders of the one recipe in --recipes trained outside this script, by the trainer's own command
    (e.g. in an earlier session): each joins the row if its logged arguments are the recipe's, for this task, budget
    and --eval-episodes (only where and how it logged may differ); its seed may not be in --seeds. A run that
    ``--resume`` continued across sessions joins whole, if every session logged the same arguments"""
    adopt_base: list[Path] = field(default_factory=list)
    """for a two-stage recipe (teacher-student-rgbd(-sel), ppo-finetune-state), the first stage's run folder of each
    --adopt run, in the same order"""
    stop_after_min: Optional[float] = None
    """stop training after this many minutes of this invocation (a session's share): the run then training is
    interrupted at its checkpoint, and the same command run again continues it and every unfinished run (their
    folders in --out-dir/runs are kept), reads the finished ones from their summary.json, and puts only finished runs
    in the rows (with --merge, a seed's earlier run stays until its new one finishes)"""
    update_results: bool = False
    """rewrite the Learning section of benchmarks/RESULTS.md with this run's table"""
    render_only: bool = False
    """train nothing: rewrite the task's Learning section of benchmarks/RESULTS.md from learning.json in --out-dir"""
    quick: bool = False
    """smoke run: dagger-state, ppo-state, ppo-finetune-state and sac-scratch-state, one seed, toy sizes, 2 evaluation
    episodes"""
    bootstrap: int = 10_000
    """bootstrap resamples"""
    reference_steps: int = REFERENCE_STEPS
    """steps of reference_speed's fixed workload timed before and after each run this invocation trains (0: none)"""


# ----------------------------------------------------------------------------- statistics


def summarise(name: str, obs: str, runs: list[dict], args: Args, rng: np.random.Generator) -> dict:
    per_seed = [r["successes"] for r in runs]
    lo, hi = bootstrap_ci(per_seed, args.bootstrap, rng)
    return dict(
        recipe=name,
        obs=obs,
        seeds=[r.get("seed") for r in runs],
        success_mean=float(np.mean([r["success_rate"] for r in runs])),
        success_ci95=[lo, hi],
        success_iqm=iqm([r["success_rate"] for r in runs]),
        per_seed=[r["success_rate"] for r in runs],
        env_steps_mean=float(np.mean([r.get("env_steps", 0) for r in runs])),
        wall_clock_min_mean=float(np.mean([r.get("wall_clock_s", 0.0) for r in runs])) / 60,
        runs=runs,
    )


# ----------------------------------------------------------------------------- runs
def reference(name: str, args: Args) -> dict:
    seeds = list(range(EVAL_SEED, EVAL_SEED + args.eval_episodes))
    if name == "random":
        gen = torch.Generator().manual_seed(0)
        act = lambda obs: torch.rand(1, 5, generator=gen) * 2 - 1  # noqa: E731
        r = evaluate_on_seeds(act, args.env_id, "state", seeds)
    else:
        from maniskill_irb120.experts.rollout import run_expert

        e = run_expert(args.env_id, args.eval_episodes, EVAL_SEED)
        failed = set(e["failed_seeds"])
        r = dict(success_rate=e["success_rate"], successes=[int(s not in failed) for s in seeds])
    return dict(r, seed=None, env_steps=0, wall_clock_s=0.0)


# ----------------------------------------------------------------------------- report
def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), dpi=80)
    for row in rows:
        if row["recipe"] in REFERENCES:
            for ax in axes:
                ax.axhline(row["success_mean"], ls="--", lw=1, color="k" if row["recipe"] == "expert" else "grey")
            continue
        for i, run in enumerate(row["runs"]):
            c = run["curve"]
            label = row["recipe"] if i == 0 else None
            color = f"C{list(RECIPES).index(row['recipe'])}"
            success = smoothed(c["success"])
            axes[0].plot(c["env_steps"], success, color=color, lw=1, alpha=0.8, label=label)
            axes[1].plot(c["wall_min"], success, color=color, lw=1, alpha=0.8)
            # where each run ended, at its held-out success; a two-stage run's first stage, hollow, where it ended
            ends = [(run, dict(color=color))]
            if "base" in run:
                ends.append((run["base"], dict(markerfacecolor="white", markeredgecolor=color)))
            for end, style in ends:
                x = (end["env_steps"], end["wall_clock_s"] / 60)
                for ax, xi in zip(axes, x):
                    ax.plot([xi], [end["success_rate"]], "o", ms=4, zorder=3, **style)
    axes[0].set(xlabel="env steps (thousands)", ylabel="training-episode success", ylim=(-0.05, 1.05))
    axes[0].xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: f"{x / 1000:g}"))
    axes[1].set(xlabel="wall clock (min)", ylim=(-0.05, 1.05))
    axes[0].legend(fontsize=7, loc="center left")
    fig.suptitle(
        "lines: training episodes, trailing mean (DAgger: β-mixed with the expert or teacher early, then the noisy "
        "learner)\ndots: held-out success where each run ended (hollow: a two-stage run's first stage); dashed: "
        "expert (black), random (grey) on the held-out seeds",
        fontsize=7,
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def markdown(rows: list[dict]) -> str:
    lines = [
        "| recipe | obs | seeds | success mean | 95 % CI | IQM | per seed | env steps | wall clock (min) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lo, hi = r["success_ci95"]
        seeds = "–" if r["recipe"] in REFERENCES else len(r["seeds"])
        per = ", ".join(f"{x:.2f}" for x in r["per_seed"])
        lines.append(
            f"| {r['recipe']} | {r['obs']} | {seeds} | {r['success_mean']:.2f} | [{lo:.2f}, {hi:.2f}] | "
            f"{r['success_iqm']:.2f} | {per} | {r['env_steps_mean']:,.0f} | {r['wall_clock_min_mean']:.1f} |"
        )
    stages = stage_lines(rows)
    return "\n".join(lines) + (f"\n\n{stages}" if stages else "")


def stage_lines(rows: list[dict]) -> str:
    """Each stage of the two-stage rows, seed by seed: the row counts both stages' env steps and minutes, and a
    reader needs to see what the first stage (a teacher, a base) reached on its own held-out episodes."""
    blocks = []
    for r in rows:
        runs = [run for run in r.get("runs", []) if "base" in run]
        if not runs:
            continue
        first = RECIPES[r["recipe"]].base.recipe
        lines = [f"{r['recipe']}, stage by stage (held-out success, env steps, minutes):", ""]
        for run in runs:
            base = run["base"]
            steps, minutes = run["env_steps"] - base["env_steps"], (run["wall_clock_s"] - base["wall_clock_s"]) / 60
            ref = run.get("reference_sps")
            lines.append(
                f"- seed {run['seed']}: {first} {base['success_rate']:.2f}, {base['env_steps']:,}, "
                f"{base['wall_clock_s'] / 60:.1f}; then {r['recipe']} {run['success_rate']:.2f}, {steps:,}, "
                f"{minutes:.1f}" + ("" if ref is None else f" (reference env steps/s before / after: {ref[0]:.0f} / "
                                     f"{ref[1]:.0f})")
            )  # fmt: skip
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def carried_rows(path: Path, retrained: list[str]) -> list[dict]:
    """The trained rows of an earlier report that this run does not replace, stamped with their provenance."""
    if not path.is_file():
        raise FileNotFoundError(f"--merge: no earlier report at {path}")
    old = json.loads(path.read_text())
    rows = [r for r in old["rows"] if r["recipe"] not in REFERENCES and r["recipe"] not in retrained]
    return [dict(r, command=r.get("command", old["command"]), date=r.get("date", old["date"])) for r in rows]


def earlier_runs(path: Path, recipe: str, seeds: list[int]) -> list[dict]:
    """The runs of an earlier report's ``recipe`` row whose seeds this run does not retrain, stamped with their
    provenance, so one row can gather its seeds from several sessions."""
    old = json.loads(path.read_text())
    for row in old["rows"]:
        if row["recipe"] == recipe:
            cmd, date = row.get("command", old["command"]), row.get("date", old["date"])
            return [
                dict(run, benchmark_command=run.get("benchmark_command", cmd), date=run.get("date", date))
                for run in row.get("runs", [])
                if run.get("seed") not in seeds
            ]
    return []


def finished_earlier(recipe: str, seed: int, args: Args) -> bool:
    """Whether a continued session (``--stop-after-min``) finds ``recipe``'s run of ``seed`` finished in its folder,
    so that ``run_trainer`` reads it from its summary.json and nothing of it trains in this session."""
    last_stage = args.out_dir / "runs" / run_name(recipe, seed)  # written after the first stage's
    return args.stop_after_min is not None and finished_summary(last_stage) is not None


def reported_provenance(recipe: str, seed: int, args: Args) -> dict:
    """What the earlier report (``--merge``) says of when and how ``recipe``'s run of ``seed`` was trained and at what
    reference speed, for a run read again from its folder; empty when the report lacks it."""
    path = args.out_dir / "learning.json"
    if not args.merge or not path.is_file():
        return {}
    keys = ("benchmark_command", "date", "reference_sps")
    runs = [r for r in earlier_runs(path, recipe, []) if r.get("seed") == seed]
    return {k: runs[0][k] for k in keys if k in runs[0]} if runs else {}


def reported_and_not_here(recipe: str, seed: int, args: Args) -> Optional[str]:
    """The date of ``recipe``'s run of ``seed`` in the earlier report when a continued session (``--merge`` with
    ``--stop-after-min``) should keep it rather than train it again: it is in the report and this machine has none of
    its run folders (a fresh clone, or a machine whose runs were cleared), so "the same command again" continues a
    multi-session benchmark from wherever it is run. None when the seed is to be trained or continued."""
    if not args.merge or args.stop_after_min is None:
        return None
    runs_dir = args.out_dir / "runs"
    names = [run_name(recipe, seed)] + ([run_name(recipe, seed, base=True)] if RECIPES[recipe].base else [])
    if any((runs_dir / name).exists() for name in names):
        return None
    path = args.out_dir / "learning.json"
    old = json.loads(path.read_text())
    for row in old["rows"]:
        if row["recipe"] == recipe:
            for run in row.get("runs", []):
                if run.get("seed") == seed:
                    return str(run.get("date", row.get("date", old.get("date", "undated"))))
    return None


def section_head(env_id: str) -> str:
    """The RESULTS.md heading of a task's Learning section (TableClearing's predates the others)."""
    if env_id == DEFAULT_ENV:
        return "## Learning — `benchmarks/learning.py`"
    return f"## Learning on {env_id} — `benchmarks/learning.py --env-id {env_id}`"


def default_out_dir(env_id: str) -> Path:
    base = Path("benchmarks/results/learning")
    return base if env_id == DEFAULT_ENV else base / env_id


def update_results(report: dict, table: str, results: Path) -> None:
    """Replace the task's ``## Learning`` section of RESULTS.md (up to the next ``## ``) with this run's."""
    head = section_head(report.get("env_id", DEFAULT_ENV))
    raw = Path(report.get("out_dir", "benchmarks/results/learning"))
    raw = (raw if raw.is_absolute() else ROOT / raw).resolve()
    try:
        raw = raw.relative_to((ROOT / "benchmarks").resolve())
    except ValueError:  # a report written outside the repository links to where it lies
        pass
    earlier = "".join(
        f"{r['recipe']}: `{r['command']}` ({r['date']}); "
        for r in report["rows"]
        if r.get("date") not in (None, report["date"])
    )
    earlier += "".join(
        f"{r['recipe']} seed {run['seed']}: `{run['benchmark_command']}` ({run['date']}); "
        for r in report["rows"]
        if r.get("date") == report["date"]
        for run in r.get("runs", [])
        if run.get("date") not in (None, report["date"])
    )
    earlier = (
        f" Rows and runs carried over from earlier runs (`--merge`, `--adopt`): {earlier.rstrip('; ')}."
        if earlier
        else ""
    )
    section = (
        f"{head}\n\nCommand: `{report['command']}` ({report['date']}, {report['machine']}, "
        f"{report['wall_min']:.0f} min).{earlier} Held-out seeds {EVAL_SEED}.. "
        f"({report['eval_episodes']} episodes per run); "
        f"raw data: [`{raw}/learning.json`]({raw}/learning.json).\n\n{table}\n\n"
        f"![learning curves]({raw}/learning.png)\n\n"
    )
    replace_section(results, head, section)


def quick_recipes(recipes: list[str]) -> list[str]:
    """The recipes a --quick run trains of ``recipes``: those of QUICK_RECIPES, else dagger-state."""
    return [r for r in recipes if r in QUICK_RECIPES] or ["dagger-state"]


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any run or reference (``benchmarks.lib.cli`` makes
    it one line and exit status 2): an unknown recipe or --env-id, a negative reference workload, a budget that is not
    positive, --env-step-budgets for a recipe without committed env steps, --adopt with other than one recipe or a run
    folder that is not there, --adopt-base not one per --adopt, --merge or --render-only without the learning.json
    they read. Whether an adopted run was trained by the recipe is read from its logs by ``main``, before any run."""
    out_dir = args.out_dir or default_out_dir(args.env_id)
    if args.render_only:
        if not (out_dir / "learning.json").is_file():
            raise FileNotFoundError(f"--render-only reads {out_dir / 'learning.json'} (--out-dir): no such file")
        return
    unknown = set(args.recipes) - set(RECIPES)
    if unknown:
        raise ValueError(f"--recipes: unknown recipes {sorted(unknown)}; choose from {sorted(RECIPES)}")
    if args.reference_steps < 0:
        raise ValueError(f"--reference-steps must be >= 0 (0: no reference), got {args.reference_steps}")
    for flag, value in (("--total-env-steps", args.total_env_steps), ("--max-minutes", args.max_minutes)):
        if value is not None and not value > 0:
            raise ValueError(f"{flag} must be positive, got {value}")
    for recipe in args.recipes:  # a recipe without env steps to take is refused before any run
        steps_for(recipe, args)
    if args.env_id not in RL_BUDGET_MIN:
        raise ValueError(f"unknown --env-id {args.env_id!r}; choose from {sorted(RL_BUDGET_MIN)}")
    recipes = quick_recipes(args.recipes) if args.quick else args.recipes
    if args.adopt and len(recipes) != 1:
        raise ValueError(f"--adopt: name the one recipe the adopted runs belong to in --recipes, not {recipes}")
    if args.adopt_base and len(args.adopt_base) != len(args.adopt):
        raise ValueError(f"--adopt-base: one first stage per adopted run: {len(args.adopt_base)} for {len(args.adopt)}")
    for flag, paths in (("--adopt", args.adopt), ("--adopt-base", args.adopt_base)):
        for path in paths:
            if not path.is_dir():
                raise FileNotFoundError(f"{flag} {path}: no such run folder")
    if args.merge and not (out_dir / "learning.json").is_file():  # refused before hours of training
        raise FileNotFoundError(f"--merge: no earlier report at {out_dir / 'learning.json'}")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        out_dir = args.out_dir or default_out_dir(args.env_id)
        report = json.loads((out_dir / "learning.json").read_text())
        plot(report["rows"], out_dir / "learning.png")
        update_results(report, markdown(report["rows"]), ROOT / "benchmarks" / "RESULTS.md")
        return report
    if args.quick:
        args.recipes = quick_recipes(args.recipes)
        args.seeds, args.budget_min, args.eval_episodes, args.bootstrap = args.seeds[:1], 0.05, 2, 200
        args.rl_budget_min = args.vision_budget_min = 0.05
    args.out_dir = args.out_dir or default_out_dir(args.env_id)
    args.rl_budget_min = args.rl_budget_min or RL_BUDGET_MIN[args.env_id]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if args.adopt_base:  # refused before any run
        adopted = [adopted_pair(args.recipes[0], b, r, args) for b, r in zip(args.adopt_base, args.adopt)]
    else:
        adopted = [adopted_run(args.recipes[0], run_dir, args) for run_dir in args.adopt]
    seeds = [r["seed"] for r in adopted] + list(args.seeds)
    if len(set(seeds)) < len(seeds):
        raise ValueError(
            f"--adopt: a seed is adopted twice or also in --seeds: adopted {seeds[: len(adopted)]}, "
            f"--seeds {args.seeds}"
        )
    rng = np.random.default_rng(0)
    t0 = time.time()
    deadline = None if args.stop_after_min is None else t0 + 60 * args.stop_after_min
    command = "python -m benchmarks.learning " + " ".join(sys.argv[1:])
    date = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    trained, unfinished, interrupted = {}, [], False
    for recipe in args.recipes:
        trained[recipe] = list(adopted)
        for seed in args.seeds:
            kept = reported_and_not_here(recipe, seed, args)
            if kept is not None:  # its earlier run stays in the row (earlier_runs)
                print(
                    f"[learning] {recipe} seed {seed}: finished in the report ({kept}) and has no run folder on this "
                    "machine, so it is kept, not trained again (without --stop-after-min it would be)",
                    flush=True,
                )
                continue
            done = finished_earlier(recipe, seed, args)  # read from its summary.json: this machine's speed now
            try:  # after a Ctrl-C, no run starts, and the report gets the runs finished before it
                timed = not (interrupted or done)
                before = reference_speed(args.reference_steps, quick=args.quick) if timed else None
                run = None if interrupted else train_run(recipe, seed, args, deadline)
            except (Interrupted, KeyboardInterrupt):  # KeyboardInterrupt: while the reference workload was timed
                run, interrupted = None, True
            if run is None:
                unfinished.append(f"{recipe} seed {seed}")
                continue
            trained[recipe].append(dict(run, benchmark_command=command, date=date))
            if done:  # it keeps the provenance and reference the session that trained it reported
                trained[recipe][-1].update(reported_provenance(recipe, seed, args))
            if before is None:
                continue
            try:  # this session's part of the run: one that resumed began in an earlier one
                after = reference_speed(args.reference_steps, quick=args.quick)
            except KeyboardInterrupt:  # the run is kept, without the machine's speed after it
                interrupted = True
                continue
            trained[recipe][-1]["reference_sps"] = [before, after]
            print(f"[learning] {recipe} seed {seed}: reference env steps/s before and after: {before:g}, {after:g}",
                  flush=True)  # fmt: skip
    if unfinished:
        print(f"[learning] unfinished, continued by the same command: {', '.join(unfinished)}", flush=True)
        if not any(trained.values()):  # nothing to add: the report stays as it is
            if interrupted:
                raise SystemExit(130)  # a Ctrl-C's exit status, so that a chain of commands stops here
            return dict(unfinished=unfinished)
    rows = [summarise(ref, "state", [reference(ref, args)], args, rng) for ref in REFERENCES]
    for recipe, runs in trained.items():
        if args.merge:  # the seeds finished now replace their earlier runs; the others' earlier runs stay
            runs += earlier_runs(args.out_dir / "learning.json", recipe, [r["seed"] for r in runs])
        if runs:
            runs.sort(key=lambda r: r["seed"])
            rows.append(dict(summarise(recipe, RECIPES[recipe].obs, runs, args, rng), command=command, date=date))
    if args.merge:
        rows += carried_rows(args.out_dir / "learning.json", [r["recipe"] for r in rows])
    report = dict(
        command=command,
        date=date,
        machine=f"{platform.node()} {platform.machine()}, {torch.get_num_threads()} torch threads",
        wall_min=(time.time() - t0) / 60,
        eval_episodes=args.eval_episodes,
        env_id=args.env_id,
        out_dir=str(args.out_dir),
        budget_min=args.budget_min,
        long_budget_min=args.long_budget_min,
        rl_budget_min=args.rl_budget_min,
        vision_budget_min=args.vision_budget_min or VISION_BUDGET_MIN[args.env_id],
        total_env_steps=args.total_env_steps,
        env_step_budgets=args.env_step_budgets,
        max_minutes=args.max_minutes,
        rows=rows,
    )
    (args.out_dir / "learning.json").write_text(json.dumps(report, indent=1))
    plot(rows, args.out_dir / "learning.png")
    table = markdown(rows)
    print(table)
    if args.update_results:
        update_results(report, table, ROOT / "benchmarks" / "RESULTS.md")
    if interrupted:
        raise SystemExit(130)
    return report


if __name__ == "__main__":
    entry("benchmarks.learning", Args, main, check)
