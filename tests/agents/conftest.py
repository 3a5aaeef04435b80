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


@pytest.fixture
def refused(capsys):
    """``refused(module, argv, says)``: the trainer's command line ``argv`` ends before anything runs, in one line on
    stderr starting ``MODULE: error: SAYS``, exit status 2."""
    import importlib

    from agents.common import entry

    def check(module: str, argv: list[str], says: str) -> None:
        ran = []
        with pytest.raises(SystemExit) as stop:
            entry(importlib.import_module(module).Args, module, ran.append, argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and not ran and err.count("\n") == 1
        assert err.startswith(f"{module}: error: {says}")

    return check
