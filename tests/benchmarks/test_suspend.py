"""A benchmark cell's wall clock leaves out the time its process was stopped (kill -STOP, as for a CI run)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

CHILD = """
import sys, time
from benchmarks.lib.suspend import Suspensions
s = Suspensions(tick_s=0.05, gap_s=0.5)
print("ready", flush=True)
time.sleep(0.3)  # running: no gap is counted
sys.stdin.readline()  # the parent stops and continues this process meanwhile
time.sleep(0.2)  # the watcher's first tick after the stop
print(s.total_s, flush=True)
"""


def test_a_stopped_process_counts_its_stop_and_a_running_one_nothing():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    child = subprocess.Popen([sys.executable, "-c", CHILD], env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)  # fmt: skip
    try:
        assert child.stdout.readline().strip() == "ready"
        time.sleep(0.5)
        child.send_signal(signal.SIGSTOP)
        time.sleep(2.0)
        child.send_signal(signal.SIGCONT)
        out, _ = child.communicate("go\n", timeout=30)
    finally:
        child.kill()
    stopped = float(out.strip())
    assert 1.5 < stopped < 2.6, stopped  # the 2 s stop, less a tick, give or take the signals' timing


def test_a_running_budget_counts_no_stop_and_bad_ticks_are_refused():
    from benchmarks.algorithms import Budget
    from benchmarks.lib.suspend import Suspensions

    clock = Budget(None, spent_s=10.0, every_s=60.0, total_steps=100, stopped_before_s=5.0)
    time.sleep(0.1)
    assert clock.stopped_s == 5.0 and 10.0 < clock.spent_s < 12.0  # earlier sessions' counts carry on
    for tick, gap in ((0.0, 1.0), (2.0, 1.0)):
        with pytest.raises(ValueError, match="tick_s"):
            Suspensions(tick_s=tick, gap_s=gap)


def test_the_table_names_a_cells_stopped_minutes_beside_its_wall_clock():
    from benchmarks.algorithms import markdown

    row = dict(name="sb3-sac-tuned", from_reward=True, obs="state", task="GraspLift", library="SB3", seeds=[1],
               success_mean=1.0, success_ci95=[0.96, 1.0], interval="Wilson", per_seed=[1.0], held_out_at={},
               env_steps_mean=500_000, wall_clock_min_mean=180.0, stopped_min_mean=0.0, cpu_steal_mean=None,
               reference_sps_mean=None, settings="-")  # fmt: skip
    assert "| 180.0 |" in markdown([row])
    assert "| 180.0 (and 43.0 stopped) |" in markdown([dict(row, stopped_min_mean=43.0)])


def test_a_stop_during_a_held_out_point_is_left_out_of_the_wall_clock_once(monkeypatch):
    """A held-out point's seconds leave the clock (it is not training); a stop within them is already left out."""
    import benchmarks.algorithms as alg

    now = [1000.0]
    monkeypatch.setattr(alg.time, "time", lambda: now[0])
    clock = alg.Budget(None, spent_s=0.0, every_s=60.0, total_steps=100)
    clock.suspensions.close()
    clock.suspensions = type("Stops", (), {"total_s": 0.0})()

    def held_out(*_args):
        now[0] += 8.0  # the evaluation took 8 s of wall clock, 5 of them stopped
        clock.suspensions.total_s = 5.0
        return dict(success_rate=0.0, successes=[False])

    monkeypatch.setattr(alg, "held_out", held_out)
    held = []
    alg.held_out_point(lambda flat: None, "GraspLift-IRB120-v1", "state", alg.Args(), 10, clock, held)
    assert clock.spent_s == 0.0 and clock.stopped_s == 5.0 and held[0][4] == 3.0
