"""Shared by the trainer tests: the smallest DAgger run (the cheapest trainer run there is)."""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_DAGGER = dict(
    budget_min=0.05,
    # a few hundred rows at most: the default ring preallocates 300,000 (~10 GB of virtual memory from the camera),
    # resident in full wherever torch's deterministic mode fills torch.empty's memory (tests/conftest.py says when)
    capacity=2_000,
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


TINY_PPO_RGBD = dict(
    env_id="GraspLift-IRB120-v1",
    obs="rgbd",
    num_envs=2,
    num_steps=8,
    num_minibatches=2,
    update_epochs=1,
    eval_freq=0,
    save_freq=1,
    exp_name="t",
    progress=False,
    total_env_steps=16,
    env_kwargs=dict(max_episode_steps=5),
)


@pytest.fixture(scope="session")
def tiny_ppo_rgbd():
    """``args(runs_dir, **overrides)``: the smallest camera PPO run's agents.ppo Args (one 16-step iteration of
    5-step episodes on 2 CPU envs)."""
    from agents.ppo import Args

    return lambda runs_dir, **kw: Args(**{**TINY_PPO_RGBD, "runs_dir": runs_dir, **kw})


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
