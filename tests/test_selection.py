"""Checkpoint selection on validation seeds: the shared core (``integrations.selection``) and skrl's hook around an
agent's ``post_interaction``. The episodes themselves are replaced by a scripted count of successes here; the
benchmark tests train SB3 and skrl cells with the hooks in physics."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from maniskill_irb120.integrations import selection
from maniskill_irb120.integrations.progress import VALIDATION_SEED


def scripted(monkeypatch, wins: list[int]) -> list[tuple]:
    """``held_out_success`` answering ``wins`` in turn; returns the calls it got (env id, obs, episodes, seed)."""
    calls, left = [], iter(wins)

    def fake(act, env_id, obs, episodes, *, seed):
        calls.append((env_id, obs, episodes, seed))
        return next(left)

    monkeypatch.setattr(selection, "held_out_success", fake)
    return calls


def test_the_best_by_success_is_kept_ties_go_to_the_earlier_and_a_resumed_run_neither_repeats_nor_skips(
    tmp_path, monkeypatch
):
    calls = scripted(monkeypatch, [1, 3, 3, 2, 4, 0])
    saved = []
    sel = selection.ValidationSelection(every=100, episodes=4, save_path=tmp_path / "best", verbose=0)
    sel.start(0)
    checked = []
    for steps in (50, 100, 150, 200, 250, 300, 400):
        if sel.due(steps):
            checked.append(steps)
            sel.validate(steps, None, "GraspLift-IRB120-v1", "state", lambda folder, s=steps: saved.append((s, folder)))
    assert checked == [100, 200, 300, 400]
    assert calls[0] == ("GraspLift-IRB120-v1", "state", 4, VALIDATION_SEED)
    assert saved == [(100, tmp_path / "best"), (200, tmp_path / "best")]  # 0.75 at 300 ties 200's: the earlier stays
    assert sel.best == dict(env_steps=200, success=0.75, episodes=4, first_seed=VALIDATION_SEED)
    kept = json.loads((tmp_path / "best" / "best.json").read_text())
    assert kept["best"] == sel.best and kept["checks"] == [[100, 0.25], [200, 0.75], [300, 0.75], [400, 0.5]]
    assert not list((tmp_path / "best").glob("*.tmp"))

    # a resumed run (its checkpoint at 350, its last check at 400) reads what was kept and goes on from there
    again = selection.ValidationSelection(every=100, episodes=4, save_path=tmp_path / "best", verbose=0)
    again.start(350)
    assert again.best == sel.best and again.checks == kept["checks"]
    assert not again.due(450) and again.due(500)
    again.validate(500, None, "GraspLift-IRB120-v1", "state", lambda folder: saved.append((500, folder)))
    assert again.best["env_steps"] == 500 and saved[-1][0] == 500
    # a step that jumps several checks' worth takes one check, and the next is due after it
    assert again.due(830) and not again.due(899) and again.due(900)


@pytest.mark.parametrize(
    "kwargs, named",
    [
        (dict(every=0), "every (0)"),
        (dict(every=100, episodes=-1), "episodes (-1)"),
        (dict(every="often"), "'often'"),
    ],
)
def test_a_bad_schedule_is_refused_by_name(kwargs, named):
    with pytest.raises(ValueError, match="ValidationSelection") as e:
        selection.ValidationSelection(**kwargs)
    assert named in str(e.value)


class FakeAgent:
    """What the hook touches of an skrl agent: its ``post_interaction`` (recording the timesteps it was called
    with), ``save`` and ``track_data``."""

    def __init__(self):
        self.posts, self.saved, self.tracked = [], [], []

    def post_interaction(self, *, timestep, timesteps):
        self.posts.append(timestep)

    def save(self, path):
        self.saved.append(path)

    def track_data(self, tag, value):
        self.tracked.append((tag, value))


def test_the_skrl_hook_counts_env_steps_from_where_a_resumed_run_stands_and_runs_after_the_agents_update(
    tmp_path, monkeypatch
):
    pytest.importorskip("skrl")
    from maniskill_irb120.integrations.skrl import SelectOnValidation

    calls = scripted(monkeypatch, [0, 2])
    agent = FakeAgent()
    env = SimpleNamespace(num_envs=4, observation_space=None)
    hook = SelectOnValidation(every=100, episodes=2, save_path=str(tmp_path / "best"), verbose=0)
    hook.attach(agent, env, "TableClearing-IRB120-v1", env_steps=1000)  # skrl's timesteps restart at 0
    for t in range(60):
        agent.post_interaction(timestep=t, timesteps=60)
    assert agent.posts == list(range(60))  # the agent's own post_interaction still runs, every step
    # 1000 + (t + 1) * 4 crosses 1100 at t = 24 and 1200 at t = 49
    assert [c[0] for c in hook.checks] == [1100, 1200] and calls[0][:3] == ("TableClearing-IRB120-v1", "state", 2)
    assert agent.saved == [str(tmp_path / "best" / "best_agent.pt")] * 2  # 0.0, then 1.0: both the best when made
    assert agent.tracked == [("Eval / Validation success", 0.0), ("Eval / Validation success", 1.0)]
    with pytest.raises(ValueError, match="obs must be 'state' or 'rgbd', not 'rgb'"):
        hook.attach(FakeAgent(), env, "TableClearing-IRB120-v1", obs="rgb")
