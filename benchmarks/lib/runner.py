"""Trainers run as subprocesses: the command a recipe's run gets, a deadline at which the trainer is interrupted at
its checkpoint, Ctrl-C and SIGTERM handled the same way, the trainer stopped with its parent (``prctl``), a run
continued with its own ``--resume``, and its result line checked and joined with its curve. Learning and the
algorithm table run their trainers through it, so a row of either means the same."""

from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np

from agents.common.logging import read_scalars
from agents.recipes import RECIPES
from benchmarks.lib import machine
from benchmarks.lib.budget import budget_flags, budget_for, rest_of, steps_for
from maniskill_irb120.errors import terminate_as_interrupt

ROOT = Path(__file__).resolve().parents[2]


def seeded(flags: list[str], seed) -> list[str]:
    """A recipe's flags for one seed (a flag may name a file per seed, e.g. the policy it starts from)."""
    return [f.replace("{seed}", str(seed)) for f in flags]


# what a trainer's result (its last printed line, or its summary.json) must carry, and what a row keeps of it
RESULT_NEEDS = {"success_rate", "successes", "env_steps", "wall_clock_s"}


# selected: agents.ppo's or agents.dagger's --select-episodes choice (the checkpoint the held-out episodes scored)
RESULT_KEPT = (
    *sorted(RESULT_NEEDS),
    *("grasped_rate", "lifted_rate", "stacked_rate", "collided_rate", "checkpoint", "selected"),
    *("total_env_steps", "stopped_early", "held_out_curve", "selection_checks"),
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
        "--total-env-steps",
        "16",
        "--eval-freq",
        "0",
        "--select-episodes",
        "1",
    ],
    "agents.sac": ["--num-envs", "1", "--learning-starts", "8", "--batch-size", "8"],
}


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


def run_name(recipe: str, seed: int, *, base: bool = False) -> str:
    """The folder name, under ``--out-dir``/runs, of ``recipe``'s run of ``seed`` (``base``: a two-stage recipe's
    first stage; without it, its last)."""
    return f"{recipe}__s{seed}" + ("__base" if base else "")


def finished_summary(run_dir: Path) -> Optional[Path]:
    """The summary.json a finished run leaves in its folder (a trainer writes it last); None while it has none."""
    summary = run_dir / "summary.json"
    return summary if summary.is_file() else None


def train_run(recipe: str, seed: int, args, deadline: Optional[float] = None) -> Optional[dict]:
    """One run of ``recipe`` (both stages of a two-stage one); None when ``deadline`` (``--stop-after-min``) cut it
    short, to be continued by the same command."""
    r = RECIPES[recipe].for_task(args.env_id)
    module, flags = r.trainer, r.argv()
    steps = steps_for(recipe, args)
    budget = budget_for(recipe, args) if steps is None else args.max_minutes
    total, base_steps = steps or (None, None)
    resume = args.stop_after_min is not None
    if r.base is None:
        return run_trainer(
            run_name(recipe, seed), module, flags, seed, budget, args, env_steps=total, resume=resume, deadline=deadline
        )
    share, hand_on = r.base.share, f"--{r.base.hand_on}"
    base_recipe = RECIPES[r.base.recipe].for_task(args.env_id)
    base_module, base_flags = base_recipe.trainer, base_recipe.argv()
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
    if "selection_checks" in tuned:  # the tuned stage's checks, on the row's env-step axis as its curve
        out["selection_checks"] = [[steps + shift_steps, *rest] for steps, *rest in tuned["selection_checks"]]
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
    args,
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
        before = machine.cpu_times()
        stdout, returncode = run_logged(cmd, deadline, log, append=resume, who=f"[learning] {name}")
        steal = machine.steal_fraction(before, machine.cpu_times())
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
    keep_priority()


def keep_priority() -> None:
    """In the trainer, after its new session began: the benchmark's niceness for its whole session too. Linux's
    scheduler shares the CPU between autogroups (one per session) before it reads a process's nice value, and a new
    session's autogroup starts at nice 0, so a trainer of a benchmark under ``nice -n 19`` would otherwise take a
    full share beside work at normal priority. Raising it needs no privilege; without autogroups (another kernel or
    OS) there is no file and the nice value alone applies, as it already does."""
    nice = os.nice(0)
    if nice > 0:
        try:
            with open("/proc/self/autogroup", "w") as f:
                f.write(str(nice))
        except OSError:
            pass


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
    try:
        with terminate_as_interrupt():
            stdout, stderr = proc.communicate(timeout=None if deadline is None else max(deadline - time.time(), 0.0))
        return stdout, stderr, proc.returncode
    except subprocess.TimeoutExpired:
        return (*stopped(proc), None)
    except KeyboardInterrupt:
        print(f"[learning] interrupted: the trainer saves its checkpoint (up to {SAVE_WAIT_S} s)", flush=True)
        raise Interrupted(*stopped(proc)) from None


def stopped(proc: subprocess.Popen) -> tuple[str, str]:
    """``proc``'s stdout and stderr after one SIGINT, its checkpoint written (killed if it takes over
    ``SAVE_WAIT_S``), with this process's SIGINT and SIGTERM ignored meanwhile."""
    with signals_held():
        proc.send_signal(signal.SIGINT)
        try:
            return proc.communicate(timeout=SAVE_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.communicate()


@contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM ignored inside, their handlers given back after: a second Ctrl-C cannot cut short what
    must finish (a checkpoint written, a stopped child waited for)."""
    handlers = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
