"""Expert demos of every task in ManiSkill's trajectory format, replayed by ManiSkill's own replay tool."""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import pytest

from maniskill_irb120.experts.demos import collect_demos
from maniskill_irb120.experts.pick_place import EXPERTS

ENV_IDS = sorted(EXPERTS)


@pytest.fixture(scope="module", params=ENV_IDS)
def demos(request, tmp_path_factory):
    return collect_demos(episodes=2, seed=3, out_dir=tmp_path_factory.mktemp("demos"), env_id=request.param)


def test_files_follow_maniskill_format(demos):
    meta = json.loads(open(demos["json"]).read())
    assert meta["env_info"]["env_id"] == f"maniskill_irb120:{demos['env_id']}"
    assert meta["env_info"]["env_kwargs"]["control_mode"] == "pd_ee_delta_tool"
    assert len(meta["episodes"]) == 2 and all(e["success"] for e in meta["episodes"])
    with h5py.File(demos["h5"]) as f:
        for ep in meta["episodes"]:
            g = f[f"traj_{ep['episode_id']}"]
            assert g["actions"].shape == (ep["elapsed_steps"], 5)
            assert "env_states" in g and "success" in g


@pytest.mark.parametrize("mode", [[], ["--use-env-states"]])
def test_maniskill_replay_tool_reproduces_success(demos, mode, tmp_path):
    # a fresh interpreter that never imports maniskill_irb120 itself: the json's env id does it
    out = subprocess.run(
        [sys.executable, "-m", "mani_skill.trajectory.replay_trajectory", "--traj-path", demos["h5"], *mode],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "2/2=100.00%" in out.stdout + out.stderr
