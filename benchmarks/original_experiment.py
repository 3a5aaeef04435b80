"""The original report's experiment run again: PPO from the 84x84 hand camera on TableClearing, with the report's
reward (``reward_mode="dense"``, unchanged: -1000 per collision) and with ``normalized_dense``, for as many env
steps as fit in the budget, and the report's Figures 5.2-5.5 against env steps: the collision penalty, the grasp
reward, the drop penalty and the mean episode reward (the report's reward, the sum of its terms, in both runs).

Each run is a recipe of ``benchmarks/learning.py`` (``ppo-rgbd-dense``, ``ppo-rgbd``) trained by ``agents.ppo`` under
``runs/original_experiment/``, and resumed from its last checkpoint when this script runs again: the budget
(``--budget-min``, 150 by default) spans sessions, and ``--stop-after-min`` ends a session's share cleanly (the
trainer is stopped and continues from its checkpoint next time, losing at most its last few iterations); Ctrl-C
stops it the same way, as in ``benchmarks/learning.py``, and exits 130 after writing the report. Once a run
has finished, its row joins the learning table with ``learning.py --recipes RECIPE --adopt RUN --merge``.

    python -m benchmarks.original_experiment --stop-after-min 160            # what fits; run again to continue
    python -m benchmarks.original_experiment --update-results                # plot and write the RESULTS section
    python -m benchmarks.original_experiment --quick --out-dir /tmp/oe       # smoke run (~1 min)
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from agents.common.logging import read_scalars
from agents.recipes import RECIPES
from benchmarks.lib.budget import budget_flags
from benchmarks.lib.cli import entry
from benchmarks.lib.report import replace_section, smoothed
from benchmarks.lib.runner import QUICK_FLAGS, Interrupted, run_logged, thinned

ROOT = Path(__file__).resolve().parents[1]

ENV_ID = "TableClearing-IRB120-v1"
EXPERIMENT = ("ppo-rgbd-dense", "ppo-rgbd")
FAST = ("ppo-rgbd-dense-fast", "ppo-rgbd-fast")
"""the same two at the fast camera update (agents.recipes.PPO_CAMERA_FAST), for the report's 4M env steps on 2
cores (issue 92): ``--recipes ppo-rgbd-fast --total-env-steps 4000000`` with its own ``--out-dir``"""
# Figures 5.2-5.5 of the original report: the reward term each plots (its per-episode sum; None: the sum of all
# terms, the report's episode reward), its caption, quoted, and the optimum the caption states, drawn beside our
# curves (the report's own curves are images its text does not carry). Figure 5.4's caption says 100, but its reward
# gives only -200 per drop and nothing for not dropping, so the best a run can log there is 0, which is drawn instead
FIGURES = (
    ("r_collision", "Figure 5.2: Collision penalty. Optimum value is 0", 0.0),
    ("r_grasp", "Figure 5.3: Grasp reward. Optimum value is 100", 100.0),
    ("r_drop", "Figure 5.4: Drop penalty. Optimum value is 100", 0.0),
    (None, "Figure 5.5: Mean episode reward. Optimum value ≥ 200", 200.0),
)
CURVE_POINTS = 250
"""points kept of each curve in the JSON: the mean of consecutive logged points (one per PPO iteration, ~2,000 a
run), so the committed file stays small and still draws the figures"""
OPTIMA_NOTE = (
    "The dashed lines mark each figure's optimum as its caption states it, but for Figure 5.4: its caption gives 100, "
    "while the report's reward pays -200 per drop and nothing otherwise, so its best is 0, as drawn."
)
REPORT = "PPO (Ray RLlib) on a T4 for 4M env steps: no success; about 80M steps estimated for the optimum"


@dataclass
class Args:
    recipes: list[str] = field(default_factory=lambda: list(EXPERIMENT))
    """the runs: ppo-rgbd-dense (the report's reward) and ppo-rgbd (normalized_dense), or either at the fast camera
    update (ppo-rgbd-dense-fast, ppo-rgbd-fast)"""
    seed: int = 1
    """the training seed"""
    budget_min: float = 150.0
    """wall-clock minutes of training per run, over every session it spans (the budget the committed runs had; with
    an env-step budget, --max-minutes guards instead)"""
    total_env_steps: Optional[int] = None
    """the budget of each run in env steps instead of minutes, over every session it spans"""
    env_step_budgets: bool = False
    """each run's budget in env steps: its committed run's (agents.recipes.ENV_STEP_BUDGETS), whatever this
    machine's speed"""
    max_minutes: Optional[float] = None
    """with an env-step budget: a wall-clock guard per run; a run it stops first says so ("stopped_early")"""
    eval_episodes: int = 100
    """held-out episodes at the end of each run"""
    stop_after_min: Optional[float] = None
    """stop training after this many minutes of this invocation (the runs continue from their checkpoints next time)"""
    runs_dir: Path = ROOT / "runs" / "original_experiment"
    """where the runs train (their TensorBoard logs and checkpoints)"""
    out_dir: Path = ROOT / "benchmarks" / "results"
    """original_experiment.json and original_experiment.png go here"""
    train: bool = True
    """train (or resume) the unfinished runs first; --no-train only plots what the runs logged"""
    update_results: bool = False
    """rewrite the section of benchmarks/RESULTS.md"""
    quick: bool = False
    """smoke run: toy sizes, 2 evaluation episodes"""


def run_dir(recipe: str, args: Args) -> Path:
    return args.runs_dir / f"{recipe}__s{args.seed}"


def command(recipe: str, args: Args, resume: bool = True) -> list[str]:
    """The trainer's command for ``recipe``: a new run, or ``--resume`` of its last checkpoint (``resume=False``:
    the command that trains it from the start, as the report shows it)."""
    r = RECIPES[recipe].for_task(ENV_ID)
    flags = [*r.argv(args.seed), "--env-id", ENV_ID, "--seed", str(args.seed)]
    steps = args.total_env_steps
    if steps is None and args.env_step_budgets:
        steps = r.env_steps[0]
    minutes = args.budget_min if steps is None else args.max_minutes
    flags += [*budget_flags(minutes, steps), "--eval-episodes", str(args.eval_episodes)]
    if steps is not None:  # held-out success along the way (30 episodes each tenth), in the run's summary.json
        flags += ["--curve-points", "10", "--curve-episodes", "30"]
    flags += ["--runs-dir", str(args.runs_dir), "--exp-name", run_dir(recipe, args).name, "--no-progress"]
    flags += ["--no-capture-video"]
    if args.quick:
        flags += QUICK_FLAGS["agents.ppo"]
    latest = run_dir(recipe, args) / "checkpoints" / "latest.pt"
    if resume and latest.is_file():
        flags += ["--resume", str(latest)]
    return [sys.executable, "-m", r.trainer, *flags]


def train(recipe: str, args: Args, deadline: Optional[float]) -> str:
    """Train or resume ``recipe`` until it finishes ("done") or the deadline passes ("stopped"); nothing is started
    once the deadline has passed ("not started"). The trainer runs as ``benchmarks.lib.runner.run_until`` runs it:
    at the deadline, on Ctrl-C or SIGTERM it gets one SIGINT and is waited for while it saves its checkpoint
    (``runner.Interrupted`` is raised on, after its output is kept), and if this process is killed it still gets its
    SIGINT."""
    if (run_dir(recipe, args) / "summary.json").is_file():
        return "done"
    if deadline is not None and time.time() >= deadline:  # the run before took this session's share
        return "not started"
    cmd = command(recipe, args)
    log = args.runs_dir / "logs" / f"{run_dir(recipe, args).name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    print(f"[original] {' '.join(cmd[1:])}", flush=True)
    # each session's output after the last
    _, returncode = run_logged(cmd, deadline, log, append=True, who=f"[original] {recipe}")
    if returncode is None:
        return "stopped"  # the run continues from its last checkpoint next time
    if returncode != 0:
        raise RuntimeError(f"{recipe} exited with {returncode}; its output is in {log}")
    return "done"


def scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar the run logged, over all its TensorBoard files (one per resume), sorted by env step."""
    return {tag: [(step, value) for step, _, value in points] for tag, points in read_scalars(folder).items()}


def figures(logged: dict[str, list[tuple[int, float]]], points: int = CURVE_POINTS) -> dict:
    """Per logged point: env steps, and each figure's per-episode value (the report's reward is the sum of its
    terms, whichever reward the run trained on); more than ``points`` logged points are averaged in consecutive runs
    of equal length, each at its last env step."""
    terms = sorted(t for t in logged if t.startswith("train/return_r_"))
    if not terms:
        return dict(env_steps=[], **{name or "episode_reward": [] for name, _, _ in FIGURES})
    steps = [s for s, _ in logged[terms[0]]]
    value = {t: dict(logged[t]) for t in terms}
    out = dict(env_steps=steps)
    for name, _, _ in FIGURES:
        if name is None:
            out["episode_reward"] = [sum(value[t].get(s, 0.0) for t in terms) for s in steps]
        else:
            out[name] = [value.get(f"train/return_{name}", {}).get(s, 0.0) for s in steps]
    return thinned(out, points)


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(14, 3.2), dpi=80)
    for i, (recipe, row) in enumerate(report["runs"].items()):
        c = row["curve"]
        for ax, (name, _, _) in zip(axes, FIGURES):
            ax.plot(c["env_steps"], smoothed(c[name or "episode_reward"]), color=f"C{i}", lw=1, label=recipe)
    for ax, (_, caption, optimum) in zip(axes, FIGURES):
        ax.axhline(optimum, color="grey", ls="--", lw=0.8, label="the report's optimum")
        ax.set_title(caption.replace(". ", ".\n"), fontsize=8)  # the caption as quoted, on two lines
        ax.set_xlabel("env steps")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"PPO from the hand camera, TableClearing, trailing mean per episode; the original report: {REPORT}",
                 fontsize=8)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def summary_of(recipe: str, args: Args) -> dict:
    folder = run_dir(recipe, args)
    summary = folder / "summary.json"
    result = json.loads(summary.read_text()) if summary.is_file() else {}
    logged = scalars(folder)  # read once: the figures and the minutes so far
    row = dict(
        recipe=recipe,
        finished=summary.is_file(),
        curve=figures(logged),
        command=" ".join(command(recipe, args, resume=False)[1:]).replace(f"{ROOT}/", ""),  # as a clone has them
    )
    for k in ("success_rate", "grasped_rate", "collided_rate", "env_steps", "wall_clock_s"):
        if k in result:
            row[k] = result[k]
    c = row["curve"]
    if c["env_steps"]:
        row["env_steps_logged"] = c["env_steps"][-1]
        clock = logged.get("charts/clock_min")  # the run's training minutes, over every session so far
        if clock:
            row["minutes_logged"] = clock[-1][1]
        tail = slice(-max(1, len(c["env_steps"]) // 10), None)  # the last tenth of training
        row["last_tenth"] = {
            name or "episode_reward": float(np.mean(c[name or "episode_reward"][tail])) for name, _, _ in FIGURES
        }
    return row


def section(report: dict, args: Args) -> str:
    lines = [
        "| run | reward trained on | finished | env steps | wall clock (min) | held-out success | "
        + " | ".join(caption.split(":")[0] for _, caption, _ in FIGURES)
        + " (last tenth of training) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for recipe, r in report["runs"].items():
        mode = "dense (the report's)" if recipe.endswith("dense") else "normalized_dense"
        last = r.get("last_tenth", {})
        cells = " | ".join(f"{last[name or 'episode_reward']:.1f}" if last else "–" for name, _, _ in FIGURES)
        wall = f"{r['wall_clock_s'] / 60:.0f}" if "wall_clock_s" in r else "–"
        if "wall_clock_s" not in r and "minutes_logged" in r:
            wall = f"{r['minutes_logged']:.0f} so far"
        success = f"{r['success_rate']:.2f}" if "success_rate" in r else "–"
        steps = r.get("env_steps", r.get("env_steps_logged", 0))
        lines.append(
            f"| {recipe} | {mode} | {'yes' if r['finished'] else 'no'} | {steps:,} | {wall} | {success} | {cells} |"
        )
    return (
        "## The original report's experiment: PPO from the hand camera\n\n"
        f"The original report: {REPORT}. Here: `python -m benchmarks.original_experiment` (2-core CPU, "
        f"{budget_text(args)} per run; commands in [the JSON](results/original_experiment.json)).\n\n"
        + "\n".join(lines)
        + "\n\n![Figures 5.2-5.5](results/original_experiment.png)\n\n"
        + f"{OPTIMA_NOTE} What each run learned, and why: "
        + "[the original report's experiment](../docs/notes/original-experiment.md).\n\n"
    )


def budget_text(args: Args) -> str:
    """The runs' budget as the section states it: env steps (the committed run's, or --total-env-steps), else
    minutes."""
    if args.total_env_steps is not None:
        return f"{args.total_env_steps:,} env steps"
    return "the committed run's env steps" if args.env_step_budgets else f"{args.budget_min:g} min"


def reported_and_not_here(args: Args) -> dict[str, dict]:
    """The runs of the earlier report (``out_dir/original_experiment.json``) that are kept as it has them, neither
    trained again nor read again: their run folder is not on this machine (a fresh clone, or runs cleared), and this
    invocation only plots (``--no-train``) or is one session of a longer run (``--stop-after-min``), so a rerun never
    writes a finished run's curves over with nothing. Without either flag a missing run is trained from the start, as
    the report's command does."""
    path = args.out_dir / "original_experiment.json"
    if not path.is_file() or (args.train and args.stop_after_min is None):
        return {}
    runs = json.loads(path.read_text()).get("runs", {})
    return {r: runs[r] for r in args.recipes if r in runs and not run_dir(r, args).exists()}


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any run starts (``benchmarks.lib.cli`` makes it one
    line and exit status 2): a recipe not of the experiment, a budget or guard that is not positive,
    --env-step-budgets for a recipe without a committed run's env steps."""
    unknown = set(args.recipes) - set(EXPERIMENT + FAST)
    if unknown:
        raise ValueError(f"--recipes: unknown recipes {sorted(unknown)}; choose from {list(EXPERIMENT + FAST)}")
    for flag, value in (
        ("--budget-min", args.budget_min),
        ("--total-env-steps", args.total_env_steps),
        ("--max-minutes", args.max_minutes),
    ):
        if value is not None and not value > 0:
            raise ValueError(f"{flag} must be positive, got {value}")
    if args.env_step_budgets and args.total_env_steps is None:
        missing = [r for r in args.recipes if RECIPES[r].for_task(ENV_ID).env_steps is None]
        if missing:
            raise ValueError(
                f"--env-step-budgets: {missing} have no committed runs on {ENV_ID}; give --total-env-steps"
            )


def main(args: Args) -> dict:
    check(args)
    if args.quick:
        args.budget_min, args.eval_episodes = 0.05, 2
    deadline = None if args.stop_after_min is None else time.time() + 60 * args.stop_after_min
    kept = reported_and_not_here(args)
    status, interrupted = {}, False
    for recipe in args.recipes:  # after a Ctrl-C no run starts, and the report shows where each run stands
        if recipe in kept:
            print(f"[original] {recipe}: kept from the report, its run folder {run_dir(recipe, args)} is not here")
            status[recipe] = "kept from the report"
            continue
        if interrupted or not args.train:
            status[recipe] = "not started" if interrupted else "not trained now"
            continue
        try:
            status[recipe] = train(recipe, args, deadline)
        except Interrupted:
            status[recipe], interrupted = "stopped", True
    report = dict(
        env_id=ENV_ID,
        budget_min=args.budget_min,
        total_env_steps=args.total_env_steps,
        env_step_budgets=args.env_step_budgets,
        max_minutes=args.max_minutes,
        seed=args.seed,
        original_report=REPORT,
        status=status,
        runs={recipe: kept[recipe] if recipe in kept else summary_of(recipe, args) for recipe in args.recipes},
    )
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "original_experiment.json").write_text(json.dumps(report, indent=1))
    plot(report, args.out_dir / "original_experiment.png")
    text = section(report, args)
    print(text)
    if args.update_results:
        replace_section(ROOT / "benchmarks" / "RESULTS.md", "## The original report's experiment", text)
    if interrupted:
        raise SystemExit(130)  # a Ctrl-C's exit status, so that a chain of commands stops here
    return report


if __name__ == "__main__":
    entry("benchmarks.original_experiment", Args, main, check)
