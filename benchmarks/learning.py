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

    python benchmarks/learning.py                                  # every recipe x 3 seeds (hours: see below)
    python benchmarks/learning.py --recipes dagger-state --seeds 1 2 3
    python benchmarks/learning.py --recipes ppo-state --env-step-budgets --max-minutes 60   # the committed env steps
    python benchmarks/learning.py --quick --out-dir /tmp/lq        # CI smoke run (~3 min, no targets)
    python benchmarks/learning.py --recipes dagger-rgbd-bf16 --seeds --adopt runs/s1 runs/s2 --merge
                                 # runs trained by the trainer's own command join the row, once checked
    python benchmarks/learning.py --env-id TableClearing-IRB120-v1 --recipes teacher-student-rgbd-sel --merge \
        --stop-after-min 140     # runs longer than a session: run the same command again until none is unfinished

Budgets in env steps (``--total-env-steps`` for every run, or ``--env-step-budgets``: each recipe's committed runs'
env steps on the task, ``recipes.ENV_STEP_BUDGETS``), with ``--max-minutes`` as a guard, hold a row to the same
training whatever the host's speed, which moved several-fold between days; the reference speed before and after each
run is recorded beside it (``reference_sps``). Without them, the minutes the committed rows were held to, as then
(the issue's targets): dagger-state, dagger-rgbd-bf16 and ppo-finetune-state ``--budget-min`` (60; the
last trains its DAgger base for half of it, then fine-tunes with PPO for the rest), ppo-state and
sac-scratch-state ``--rl-budget-min`` (RL_BUDGET_MIN of the task), dagger-rgbd and sac-state
``--long-budget-min`` (120); the final evaluation is extra. A recipe's flags are the same on every task but for
TASK_FLAGS (GraspLift's ppo-state adds ``--logstd state``), and a two-stage recipe's base gets its share of the
budget from BASES but where TASK_BASE_SHARES gives a task its own. The recipes, their budgets and these tables live
in ``maniskill_irb120/recipes.py``, which the trainers' ``--recipe NAME`` reads too: a run here and a trainer
started by hand with the same recipe get the same flags. With ``--stop-after-min`` the run in progress is
interrupted at its checkpoint when the minutes are up, and the same command continues it; Ctrl-C or SIGTERM does the
same at once (``run_until``), and the exit status is then 130. ``--update-results``
rewrites the Learning section of benchmarks/RESULTS.md; ``--render-only`` redraws it and the plot from the task's
committed learning.json, training nothing.
"""

from __future__ import annotations

import ctypes
import json
import platform
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from results_md import replace_section  # noqa: E402

from agents.common import EVAL_SEED, evaluate_on_seeds  # noqa: E402
from agents.common.logging import event_files, read_scalars  # noqa: E402
from maniskill_irb120.recipes import (  # noqa: E402  (the recipes: their one home, which the trainers' --recipe reads)
    BASES,
    DEFAULT_ENV,
    LONG_BUDGET_MIN,
    RECIPES,
    RL_BUDGET_MIN,
    SHORT_BUDGET_MIN,
    VISION_BUDGET_MIN,
    base_share,
    env_step_budget,
    recipe_flags,
    seeded,
)

REFERENCES = ("random", "expert")
# what a trainer's result (its last printed line, or its summary.json) must carry, and what a row keeps of it
RESULT_NEEDS = {"success_rate", "successes", "env_steps", "wall_clock_s"}
# selected: agents.ppo's or agents.dagger's --select-episodes choice (the checkpoint the held-out episodes scored)
RESULT_KEPT = (
    *sorted(RESULT_NEEDS),
    *("grasped_rate", "lifted_rate", "stacked_rate", "collided_rate", "checkpoint", "selected"),
    *("total_env_steps", "stopped_early"),
)
# --quick: the same code paths at toy sizes
QUICK_FLAGS = {
    "agents.dagger": [
        "--num-envs",
        "1",
        "--expert-episodes",
        "1",
        "--episodes-per-round",
        "1",
        "--updates-per-round",
        "5",
        "--batch-size",
        "16",
    ],  # fmt: skip
    "agents.ppo": [
        "--num-envs",
        "1",
        "--num-steps",
        "8",
        "--num-minibatches",
        "2",
        "--total-timesteps",
        "16",
        "--eval-freq",
        "0",
        "--select-episodes",
        "1",
    ],
    "agents.sac": ["--num-envs", "1", "--learning-starts", "8", "--batch-size", "8"],
}
QUICK_RECIPES = ("dagger-state", "ppo-state", "ppo-finetune-state", "sac-scratch-state")


REFERENCE_ENV, REFERENCE_ENVS, REFERENCE_STEPS = "TableClearing-IRB120-v1", 4, 200
"""reference_speed's fixed workload: its task, CPU envs and batched steps"""


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
def bootstrap_ci(per_seed: list[list[int]], n: int, rng: np.random.Generator) -> tuple[float, float]:
    """95 % interval of the mean success: resample seeds, then episodes within each resampled seed."""
    runs = [np.asarray(s, dtype=float) for s in per_seed if len(s)]
    if not runs:
        return float("nan"), float("nan")
    means = np.empty(n)
    for i in range(n):
        pick = rng.integers(0, len(runs), len(runs))
        means[i] = np.mean([runs[j][rng.integers(0, len(runs[j]), len(runs[j]))].mean() for j in pick])
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def iqm(values: list[float]) -> float:
    """Interquartile mean (rliable's aggregate): the mean of the middle 50 % of the sorted values."""
    v = np.sort(np.asarray(values, dtype=float))
    if len(v) == 0:
        return float("nan")
    k = int(np.floor(0.25 * len(v)))
    return float(v[k : len(v) - k].mean())


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


CURVE_POINTS = 300
"""points kept of each stage's curve in the JSON: PPO logs a point per iteration (~4,000 in a 90-minute run), and
the figure draws a trailing mean over ~1/60 of a curve, which 300 bin means still give"""
CLOCKS = ("env_steps", "wall_min")
"""a curve's x-axes: a bin of points is placed at its last one's"""


def thinned(columns: dict[str, list], points: int = CURVE_POINTS) -> dict[str, list]:
    """``columns`` (equal-length lists) in at most ``points`` consecutive bins of equal length: the clocks
    (``CLOCKS``) at each bin's last point, every other column the bin's mean; returned unchanged if short enough."""
    n = len(next(iter(columns.values()), []))
    if n <= points:
        return columns
    bins = np.array_split(np.arange(n), points)
    return {
        k: [v[b[-1]] for b in bins] if k in CLOCKS else [float(np.mean(np.asarray(v, dtype=float)[b])) for b in bins]
        for k, v in columns.items()
    }


def curve(run_dir: Path) -> dict:
    """Training-episode success (as logged) against env steps and minutes of training, over every session of a
    resumed run (``agents.common.logging.read_scalars``: the minutes are the trainer's budget clock), ``thinned``."""
    points = read_scalars(run_dir).get("train/success_rate", [])
    return thinned(
        dict(
            env_steps=[step for step, _, _ in points],
            wall_min=[minutes for _, minutes, _ in points],
            success=[value for _, _, value in points],
        ),
        CURVE_POINTS,
    )


def make_room(run_dir: Path) -> Path:
    """``run_dir``, empty: an earlier run of the same recipe and seed is kept, renamed after its last change (its
    event files would otherwise mix into this run's curve)."""
    if run_dir.exists():
        stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(run_dir.stat().st_mtime))
        old = run_dir.with_name(f"{run_dir.name}.before-{stamp}")
        run_dir.rename(old)
        print(f"[learning] the earlier {run_dir.name} run was moved to {old}", flush=True)
    return run_dir


def budget_for(kind: str, args: Args) -> float:
    """Minutes per run of a recipe whose budget is ``kind`` (RECIPES: "short", "long" or "rl")."""
    if kind == "vision":
        return args.vision_budget_min or VISION_BUDGET_MIN[args.env_id]
    if kind == "rl":
        return args.rl_budget_min or RL_BUDGET_MIN[args.env_id]
    return dict(long=args.long_budget_min).get(kind) or args.budget_min


def steps_for(recipe: str, args: Args) -> Optional[tuple[int, Optional[int]]]:
    """(env steps per run of ``recipe``, its first stage's for a two-stage one), or None for a run budgeted in minutes
    (:func:`budget_for`): ``--total-env-steps``, else with ``--env-step-budgets`` the committed runs' env steps on the
    task (``recipes.ENV_STEP_BUDGETS``; a recipe without them is refused by name, before any run)."""
    committed = env_step_budget(recipe, args.env_id)
    if args.total_env_steps is not None:
        if recipe not in BASES:
            return args.total_env_steps, None
        share = committed[1] / committed[0] if committed else base_share(recipe, args.env_id)
        return args.total_env_steps, max(1, round(share * args.total_env_steps))
    if not args.env_step_budgets:
        return None
    if committed is None:
        raise ValueError(
            f"--env-step-budgets: {recipe} has no committed runs on {args.env_id} to take its env steps from "
            "(recipes.ENV_STEP_BUDGETS); give --total-env-steps"
        )
    return committed


def budget_flags(minutes: Optional[float], env_steps: Optional[int]) -> list[str]:
    """A trainer's budget flags: ``--total-env-steps`` with ``minutes`` as its ``--max-minutes`` guard (if any), or,
    for a run budgeted in minutes, ``--budget-min`` as the committed runs were started."""
    if env_steps is None:
        return ["--budget-min", f"{minutes:.4g}"]
    return ["--total-env-steps", str(env_steps)] + ([] if minutes is None else ["--max-minutes", f"{minutes:.4g}"])


def rest_of(total: Optional[float], spent: float) -> Optional[float]:
    """What a two-stage run's second stage gets of ``total`` (minutes or env steps) after its first spent ``spent``:
    at least 2 % of it, so that an overrun of the first shows in the row and the second still runs."""
    return None if total is None else max(total - spent, 0.02 * total)


def run_name(recipe: str, seed: int, *, base: bool = False) -> str:
    """The folder name, under ``--out-dir``/runs, of ``recipe``'s run of ``seed`` (``base``: a two-stage recipe's
    first stage; without it, its last)."""
    return f"{recipe}__s{seed}" + ("__base" if base else "")


def finished_summary(run_dir: Path) -> Optional[Path]:
    """The summary.json a finished run leaves in its folder (a trainer writes it last); None while it has none."""
    summary = run_dir / "summary.json"
    return summary if summary.is_file() else None


def train_run(recipe: str, seed: int, args: Args, deadline: Optional[float] = None) -> Optional[dict]:
    """One run of ``recipe`` (both stages of a two-stage one); None when ``deadline`` (``--stop-after-min``) cut it
    short, to be continued by the same command."""
    module, _, obs, kind = RECIPES[recipe]
    flags = recipe_flags(recipe, args.env_id)
    steps = steps_for(recipe, args)
    budget = budget_for(kind, args) if steps is None else args.max_minutes
    total, base_steps = steps or (None, None)
    resume = args.stop_after_min is not None
    if recipe not in BASES:
        return run_trainer(
            run_name(recipe, seed), module, flags, seed, budget, args, env_steps=total, resume=resume, deadline=deadline
        )
    base_recipe, _, hand_on = BASES[recipe]
    share = base_share(recipe, args.env_id)
    base_module, base_flags = RECIPES[base_recipe][0], recipe_flags(base_recipe, args.env_id)
    base = run_trainer(
        run_name(recipe, seed, base=True),
        base_module,
        base_flags,
        seed,
        share * budget if steps is None else budget,
        args,
        env_steps=base_steps,
        resume=resume,
        deadline=deadline,
    )
    if base is None:
        return None
    flags = [*flags, hand_on, base["checkpoint"]]
    rest = rest_of(budget, base["wall_clock_s"] / 60)  # an overrun of the base shows in the row's time
    rest_steps = None if total is None else round(rest_of(total, base["env_steps"]))
    tuned = run_trainer(
        run_name(recipe, seed), module, flags, seed, rest, args, env_steps=rest_steps, resume=resume, deadline=deadline
    )
    if tuned is None:
        return None
    out = joined(base, tuned)
    if total is not None:  # the row's budget is both stages'
        out.update(total_env_steps=total, stopped_early=bool(base.get("stopped_early") or tuned.get("stopped_early")))
    return out


def joined(base: dict, tuned: dict) -> dict:
    """One run of a two-stage recipe: the fine-tuned policy's evaluation, both stages' steps, time and curve."""
    shift_steps, shift_min = base["env_steps"], base["wall_clock_s"] / 60
    curve = {
        "env_steps": base["curve"]["env_steps"] + [x + shift_steps for x in tuned["curve"]["env_steps"]],
        "wall_min": base["curve"]["wall_min"] + [x + shift_min for x in tuned["curve"]["wall_min"]],
        "success": base["curve"]["success"] + tuned["curve"]["success"],
    }
    out = dict(tuned, env_steps=base["env_steps"] + tuned["env_steps"], curve=curve)
    out.update(
        wall_clock_s=base["wall_clock_s"] + tuned["wall_clock_s"], command=f"{base['command']} && {tuned['command']}"
    )
    if "cpu_steal" in base and "cpu_steal" in tuned:  # both stages, weighted by their minutes
        w_base, w_tuned = base["wall_clock_s"], tuned["wall_clock_s"]
        both = (base["cpu_steal"] * w_base + tuned["cpu_steal"] * w_tuned) / max(w_base + w_tuned, 1e-9)
        out["cpu_steal"] = round(both, 3)
    else:
        out.pop("cpu_steal", None)
    out["base"] = {
        k: base[k] for k in ("success_rate", "env_steps", "wall_clock_s", "checkpoint", "cpu_steal") if k in base
    }
    return out


def run_trainer(
    name: str,
    module: str,
    flags: list[str],
    seed: int,
    budget: Optional[float],
    args: Args,
    *,
    env_steps: Optional[int] = None,
    env_id: Optional[str] = None,
    runs_dir: Optional[Path] = None,
    logs_dir: Optional[Path] = None,
    resume: bool = False,
    deadline: Optional[float] = None,
) -> Optional[dict]:
    """``module`` as a subprocess for ``env_steps`` env steps with a ``budget`` minutes guard (None: none), or,
    without ``env_steps``, for ``budget`` minutes (:func:`budget_flags`), as the run ``name`` in ``runs_dir`` (default
    ``args.out_dir / "runs"``) on ``env_id`` (default ``args.env_id``), its output kept in ``logs_dir / name.log``
    (default ``args.out_dir / "logs"``); returns its checked result line with its curve. benchmarks/algorithms.py
    passes its own args (``eval_episodes`` and ``quick`` are read from them) with the other three given.

    ``resume``: the run folder is kept, not moved aside (:func:`make_room`); a run there that finished is read from
    its summary.json, not trained again, and one that left a checkpoint and no result continues with the trainer's
    own ``--resume``. ``deadline`` (a ``time.time()``): the trainer is interrupted then (it saves its checkpoint on
    the way out) and None returned, as it is when the deadline has passed before the run starts."""
    env_id = args.env_id if env_id is None else env_id
    runs_dir = args.out_dir / "runs" if runs_dir is None else runs_dir
    logs_dir = args.out_dir / "logs" if logs_dir is None else logs_dir
    cmd = [sys.executable, "-m", module, *seeded(flags, seed), "--env-id", env_id, "--seed", str(seed)]
    cmd += [*budget_flags(budget, env_steps), "--eval-episodes", str(args.eval_episodes)]
    cmd += ["--runs-dir", str(runs_dir), "--exp-name", name, "--no-progress", "--no-capture-video"]
    if args.quick:
        cmd += QUICK_FLAGS[module]
    run_dir = runs_dir / name
    latest, summary = run_dir / "checkpoints" / "latest.pt", finished_summary(run_dir)
    shown = " ".join(cmd[1:])  # the command that trains the run from the start, without a --resume
    log = logs_dir / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    steal = None
    if resume and summary is not None:
        print(f"[learning] {name}: finished earlier, read from {summary}", flush=True)
        result = json.loads(summary.read_text())
    elif deadline is not None and time.time() >= deadline:
        print(f"[learning] {name}: not started, --stop-after-min has run out", flush=True)
        return None
    else:
        if not resume:
            make_room(run_dir)
        elif latest.is_file():
            cmd += ["--resume", str(latest)]
        print(f"[learning] {name}: {' '.join(cmd[1:])}", flush=True)
        # a resumed run's log keeps each session's output
        before = cpu_times()
        stdout, returncode = run_logged(cmd, deadline, log, append=resume, who=f"[learning] {name}")
        steal = steal_fraction(before, cpu_times())
        if steal is not None:
            print(
                f"[learning] {name}: the host took {100 * steal:.0f} % of this machine's CPU time (steal)", flush=True
            )
        if returncode is None:
            print(f"[learning] {name}: stopped at --stop-after-min; the same command continues it", flush=True)
            return None
        if returncode != 0:
            raise RuntimeError(f"{name} exited with {returncode}; its output is in {log}")
        result = json.loads(stdout.strip().splitlines()[-1])
    missing = RESULT_NEEDS - set(result)
    if missing:
        raise RuntimeError(f"{name}: its result lacks {sorted(missing)}; output in {log}")
    out = {k: result[k] for k in RESULT_KEPT if k in result}
    out.update(seed=seed, command=shown, curve=curve(run_dir))
    if steal is not None:  # a run read from its summary was timed in an earlier session: unknown here
        out["cpu_steal"] = steal
    return out


def reference_speed(steps: int = REFERENCE_STEPS, *, quick: bool = False, seed: int = 0) -> Optional[float]:
    """Env steps/s of one fixed workload on this machine now: ``steps`` batched steps of seeded uniform random actions
    in ``REFERENCE_ENVS`` CPU envs of ``REFERENCE_ENV`` from state (env 0 in this process, the others in workers, as
    the trainers run theirs); None for ``steps`` 0. ``quick``: a toy version for smoke runs (5 steps of one env).

    Why: a budgeted run's env steps measure the machine as much as the method, and a shared host's speed can move
    several-fold from one day to the next while its steal (:func:`cpu_times`) stays low (docs/benchmarks.md). The
    same workload timed just before and after each run and each algorithm cell lets runs days apart be compared as
    ratios."""
    if steps < 0:
        raise ValueError(f"reference steps must be >= 0 (0: no reference), got {steps}")
    if steps == 0:
        return None
    from maniskill_irb120.vector import make_vec_env

    steps, num_envs = (min(steps, 5), 1) if quick else (steps, REFERENCE_ENVS)
    envs = make_vec_env(REFERENCE_ENV, num_envs, obs_mode="state", render_backend="none", record_metrics=False,
                        backend="cpu" if num_envs > 1 else "inprocess")  # fmt: skip
    try:
        space = envs.single_action_space
        rng = np.random.default_rng(seed)
        acts = rng.uniform(space.low, space.high, size=(steps + 5, num_envs, *space.shape)).astype(np.float32)
        envs.reset(seed=seed)
        for a in acts[:5]:  # warm-up: the first steps fill caches
            envs.step(torch.from_numpy(a))
        t0 = time.perf_counter()
        for a in acts[5:]:
            envs.step(torch.from_numpy(a))
        elapsed = time.perf_counter() - t0
    finally:
        envs.close()
    return round(steps * num_envs / elapsed, 1)


def cpu_times() -> Optional[tuple[int, int]]:
    """(steal, total) CPU time of every CPU since boot, in ticks, from Linux's ``/proc/stat``; None elsewhere.
    Steal is the time the hypervisor gave this VM's CPUs to other guests: a budgeted run gets fewer env steps in its
    minutes, and nothing on the machine itself (ps, top's process list) shows why."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if fields[:1] != ["cpu"] or len(fields) < 9:
        return None
    ticks = [int(x) for x in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return ticks[7], sum(ticks)


def steal_fraction(before: Optional[tuple[int, int]], after: Optional[tuple[int, int]]) -> Optional[float]:
    """The share of the CPU time between two :func:`cpu_times` that the host stole (0 on a machine of its own)."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return round((after[0] - before[0]) / (after[1] - before[1]), 3)


class Interrupted(Exception):
    """Ctrl-C (SIGINT) or SIGTERM reached this process while a trainer ran: the trainer was interrupted at its
    checkpoint, as at ``--stop-after-min``; ``args`` are its (stdout, stderr)."""


SAVE_WAIT_S = 600
"""how long an interrupted trainer may take to save its checkpoint and close its envs before it is killed"""


PRCTL = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None
"""libc's prctl, looked up here: between fork and exec the child should not load anything"""


def stop_with_parent() -> None:
    """In the trainer, before it starts: SIGINT, its Ctrl-C, when the process that started it dies, even by SIGKILL
    (Linux's ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing), so no trainer trains on unwatched. SIGINT is also set
    back to its default: a benchmark started in the background (``cmd &`` from a script) inherits SIGINT ignored, and
    a trainer that inherited that would never see its Ctrl-C, and would be killed unsaved after ``SAVE_WAIT_S``."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # the trainer's Python then turns it into KeyboardInterrupt
    if PRCTL is not None:
        PRCTL(1, signal.SIGINT)  # 1: PR_SET_PDEATHSIG


def run_logged(
    cmd: list[str], deadline: Optional[float], log: Path, *, append: bool, who: str
) -> tuple[str, Optional[int]]:
    """:func:`run_until` with the trainer's output (its stdout, then its stderr) written to ``log``, or added to it
    with ``append``, however the run ends: on :class:`Interrupted` the output is kept, ``who`` (e.g. ``"[learning]
    name"``) says so, and it is raised on. Returns (stdout, returncode)."""

    def keep(stdout: str, stderr: str) -> None:
        with open(log, "a" if append else "w") as f:
            f.write(stdout + "\n--- stderr ---\n" + stderr)

    try:
        stdout, stderr, returncode = run_until(cmd, deadline)
    except Interrupted as stop:
        keep(*stop.args)
        print(f"{who}: interrupted at its checkpoint; the same command continues it", flush=True)
        raise
    keep(stdout, stderr)
    return stdout, returncode


def run_until(cmd: list[str], deadline: Optional[float]) -> tuple[str, str, Optional[int]]:
    """``cmd``'s stdout, stderr and exit code; at ``deadline`` it gets SIGINT (a trainer's Ctrl-C: it saves its
    checkpoint and exits) and the code is None.

    The trainer runs in its own session, so a Ctrl-C at the terminal reaches this process alone, which then sends
    the trainer one SIGINT and waits while it saves (a second Ctrl-C is ignored meanwhile: one during the trainer's
    save would lose it) before raising :class:`Interrupted`. SIGTERM is taken the same way."""
    proc = subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=stop_with_parent,
    )
    on_term = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        stdout, stderr = proc.communicate(timeout=None if deadline is None else max(deadline - time.time(), 0.0))
        return stdout, stderr, proc.returncode
    except subprocess.TimeoutExpired:
        return (*stopped(proc), None)
    except KeyboardInterrupt:
        print(f"[learning] interrupted: the trainer saves its checkpoint (up to {SAVE_WAIT_S} s)", flush=True)
        raise Interrupted(*stopped(proc)) from None
    finally:
        signal.signal(signal.SIGTERM, on_term)


def stopped(proc: subprocess.Popen) -> tuple[str, str]:
    """``proc``'s stdout and stderr after one SIGINT, its checkpoint written (killed if it takes over
    ``SAVE_WAIT_S``), with this process's SIGINT and SIGTERM ignored meanwhile."""
    handlers = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.communicate(timeout=SAVE_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.communicate()
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)


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


def adopted_pair(recipe: str, base_dir: Path, run_dir: Path, args: Args) -> dict:
    """A two-stage run trained outside this script: the base stage checked against the base recipe at its share of
    the budget, the second against ``recipe`` with the rest of it and the base's checkpoint handed on, as
    ``train_run`` would have run them."""
    base_recipe, _, hand_on = BASES[recipe]
    share = base_share(recipe, args.env_id)
    steps = steps_for(recipe, args)
    if steps is not None:
        total, base_steps = steps
        base = adopted_run(base_recipe, base_dir, args, stage_budget=args.max_minutes, stage_steps=base_steps)
        rest, rest_steps = (
            rest_of(args.max_minutes, base["wall_clock_s"] / 60),
            round(rest_of(total, base["env_steps"])),
        )
    else:
        budget = budget_for(RECIPES[recipe][3], args)
        base = adopted_run(base_recipe, base_dir, args, stage_budget=share * budget)
        rest, rest_steps = rest_of(budget, base["wall_clock_s"] / 60), None
    extra = [hand_on, base["checkpoint"]]
    tuned = adopted_run(recipe, run_dir, args, stage_budget=rest, extra=extra, stage_steps=rest_steps)
    return dict(joined(base, tuned), adopted_from=f"{base_dir} + {run_dir}")


def adopted_run(
    recipe: str,
    run_dir: Path,
    args: Args,
    stage_budget: Optional[float] = None,
    extra: list[str] = (),
    stage_steps: Optional[int] = None,
) -> dict:
    """A finished run of ``recipe`` trained outside this script, checked against the recipe and read as
    ``run_trainer`` reads its own (its summary.json is the result line; its curve's clock starts when its log was
    opened, seconds after the process). ``stage_budget``, ``stage_steps`` and ``extra``: one stage of a two-stage
    recipe (:func:`adopted_pair`)."""
    import importlib

    module, _, _, kind = RECIPES[recipe]
    flags = [*recipe_flags(recipe, args.env_id), *extra]
    if recipe in BASES and not extra:
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
        stage_budget = budget_for(kind, args) if steps is None else args.max_minutes
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


# ----------------------------------------------------------------------------- report
def smoothed(values: list[float], points: int = 60) -> np.ndarray:
    """A trailing mean over ~1/``points`` of the curve: PPO logs a point per handful of episodes (each 0 or 1),
    which drawn raw fills the plot with a solid band."""
    v = np.asarray(values, dtype=float)
    w = max(1, len(v) // points)
    return np.array([v[max(0, i - w + 1) : i + 1].mean() for i in range(len(v))])


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
        first = BASES[r["recipe"]][0]
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
    names = [run_name(recipe, seed)] + ([run_name(recipe, seed, base=True)] if recipe in BASES else [])
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


def main(args: Args) -> dict:
    if args.render_only:
        out_dir = args.out_dir or default_out_dir(args.env_id)
        report = json.loads((out_dir / "learning.json").read_text())
        plot(report["rows"], out_dir / "learning.png")
        update_results(report, markdown(report["rows"]), ROOT / "benchmarks" / "RESULTS.md")
        return report
    unknown = set(args.recipes) - set(RECIPES)
    if unknown:
        raise ValueError(f"unknown recipes {sorted(unknown)}; choose from {sorted(RECIPES)}")
    if args.reference_steps < 0:
        raise ValueError(f"--reference-steps must be >= 0 (0: no reference), got {args.reference_steps}")
    for flag, value in (("--total-env-steps", args.total_env_steps), ("--max-minutes", args.max_minutes)):
        if value is not None and not value > 0:
            raise ValueError(f"{flag} must be positive, got {value}")
    for recipe in args.recipes:  # a recipe without env steps to take is refused before any run
        steps_for(recipe, args)
    if args.quick:
        args.recipes = [r for r in args.recipes if r in QUICK_RECIPES] or ["dagger-state"]
        args.seeds, args.budget_min, args.eval_episodes, args.bootstrap = args.seeds[:1], 0.05, 2, 200
        args.rl_budget_min = args.vision_budget_min = 0.05
    if args.env_id not in RL_BUDGET_MIN:
        raise ValueError(f"unknown --env-id {args.env_id!r}; choose from {sorted(RL_BUDGET_MIN)}")
    args.out_dir = args.out_dir or default_out_dir(args.env_id)
    args.rl_budget_min = args.rl_budget_min or RL_BUDGET_MIN[args.env_id]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if args.adopt and len(args.recipes) != 1:
        raise ValueError(f"--adopt: name the one recipe the adopted runs belong to in --recipes, not {args.recipes}")
    if args.adopt_base and len(args.adopt_base) != len(args.adopt):
        raise ValueError(f"--adopt-base: one first stage per adopted run: {len(args.adopt_base)} for {len(args.adopt)}")
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
    if args.merge and not (args.out_dir / "learning.json").is_file():  # refused before hours of training
        raise FileNotFoundError(f"--merge: no earlier report at {args.out_dir / 'learning.json'}")
    command = "python benchmarks/learning.py " + " ".join(sys.argv[1:])
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
            rows.append(dict(summarise(recipe, RECIPES[recipe][2], runs, args, rng), command=command, date=date))
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
        vision_budget_min=budget_for("vision", args),
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
    main(tyro.cli(Args))
