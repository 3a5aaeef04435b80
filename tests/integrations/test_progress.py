"""integrations.progress: the line a training run prints (steps, rate, ETA, a note), at most every ``every_s``
seconds, and the held-out seeds the trainers use."""

from __future__ import annotations

import io
import re

import pytest

from maniskill_irb120.integrations.progress import HELD_OUT_SEED, Progress, clock


def test_a_line_has_steps_rate_eta_and_the_note():
    out = io.StringIO()
    p = Progress("sb3 ppo", 1000, every_s=3600, stream=out)
    p.started -= 10.0  # ten seconds in
    p.report(250, "training success 0.10 (last 20 episodes)")
    line = out.getvalue().strip()
    m = re.fullmatch(
        r"\[sb3 ppo\] 250/1,000 env steps \(25 %\) \| (\d+\.\d) env steps/s \| 10s elapsed, ETA (\d+)s \| (.*)", line
    )
    assert m, line
    assert float(m.group(1)) == pytest.approx(25.0, abs=0.2) and int(m.group(2)) == pytest.approx(30, abs=1)
    assert m.group(3) == "training success 0.10 (last 20 episodes)"


def test_a_resumed_run_counts_its_rate_from_where_it_continued():
    out = io.StringIO()
    p = Progress("sb3 sac", 1000, every_s=3600, stream=out, start=400)
    p.started -= 10.0  # ten seconds after continuing at 400 env steps
    p.report(500)
    m = re.search(r"(\d+\.\d) env steps/s \| 10s elapsed, ETA (\d+)s$", out.getvalue().strip())
    assert m, out.getvalue()
    assert float(m.group(1)) == pytest.approx(10.0, abs=0.1) and int(m.group(2)) == pytest.approx(50, abs=1)


def test_tick_prints_only_when_due_and_asks_for_the_note_only_then():
    out, asked = io.StringIO(), []
    p = Progress("x", 100, every_s=3600, stream=out)
    assert not p.tick(10, lambda: asked.append(1) or "")
    assert out.getvalue() == "" and asked == []
    p.every_s = 0.0
    assert p.tick(20, lambda: asked.append(1) or "note")
    assert asked == [1] and out.getvalue().rstrip().endswith("| note")


def test_clock_reads_like_a_duration():
    assert [clock(s) for s in (0, 42.4, 425, 3720, float("inf"))] == ["0s", "42s", "7m05s", "1h02m", "?"]


def test_the_held_out_and_validation_seeds_are_the_trainers():
    from maniskill_irb120.integrations.progress import VALIDATION_SEED

    common = pytest.importorskip("agents.common")
    assert HELD_OUT_SEED == common.EVAL_SEED and VALIDATION_SEED == common.VALIDATION_SEED


def test_a_heartbeat_keeps_lines_coming_while_nothing_steps():
    import time

    from maniskill_irb120.integrations.progress import Heartbeat

    out = io.StringIO()
    p = Progress("sb3 ppo", 100, every_s=0.05, stream=out)
    with Heartbeat(p, 40, "updating the policy"):
        time.sleep(0.3)
    lines = out.getvalue().splitlines()
    assert len(lines) >= 3 and all("40/100 env steps" in x and "| updating the policy (" in x for x in lines), lines
    time.sleep(0.1)
    assert out.getvalue().splitlines() == lines  # stopped with the phase
