"""Shared by the trainer tests: the smallest DAgger run (the cheapest trainer run there is)."""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_DAGGER = dict(
    budget_min=0.05,
    num_envs=1,
    expert_episodes=1,
    episodes_per_round=1,
    updates_per_round=5,
    batch_size=16,
    eval_episodes=1,
    exp_name="t",
    progress=False,
    capture_video=False,
)


@pytest.fixture(scope="session")
def tiny_dagger():
    """``run(runs_dir, **overrides)``: one tiny agents.dagger run; returns its result dict."""
    from agents.dagger import Args, main

    def run(runs_dir: Path, **kw) -> dict:
        return main(Args(**{**TINY_DAGGER, "runs_dir": runs_dir, **kw}))

    return run
