"""The speed of the machine a result was measured on: one fixed workload's env steps/s (``reference_speed``), timed
before and after each run, and the CPU time the host stole meanwhile. A shared host's speed moves several-fold
between days, so results are compared in env steps, with these recorded beside them (docs/benchmarks.md)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

REFERENCE_ENV, REFERENCE_ENVS, REFERENCE_STEPS = "TableClearing-IRB120-v1", 4, 200
"""reference_speed's fixed workload: its task, CPU envs and batched steps"""


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
