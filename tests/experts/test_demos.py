"""Expert demos of every task in ManiSkill's trajectory format, replayed by ManiSkill's own replay tool; demos
recorded in pd_joint_pos are also converted by it to other control modes."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

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


@pytest.mark.parametrize(
    "demos, mode",
    [
        # the env-state replay is the same code for every task: one task's by default, the others' with -m slow
        pytest.param(env_id, mode, marks=[pytest.mark.slow] if mode and env_id != "TableClearing-IRB120-v1" else [])
        for env_id in ENV_IDS
        for mode in ([], ["--use-env-states"])
    ],
    indirect=["demos"],
    ids=[f"{env_id}-mode{i}" for env_id in ENV_IDS for i in range(2)],
)
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


# ---------------------------------------------------------------- pd_joint_pos demos, converted by ManiSkill
def replay(h5: str, *args: str, cwd) -> subprocess.CompletedProcess:
    """ManiSkill's replay tool in a fresh interpreter (the json's env id imports this package)."""
    cmd = [sys.executable, "-m", "mani_skill.trajectory.replay_trajectory", "--traj-path", h5, *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=cwd)


def converted_episodes(out: subprocess.CompletedProcess, h5: str, mode: str) -> list[dict]:
    """The episodes of the replay tool's saved trajectory in ``mode`` (saved failures too: --allow-failure)."""
    assert out.returncode == 0, out.stderr[-3000:]
    js = Path(h5).with_name(f"{Path(h5).stem}.none.{mode}.physx_cpu.json")
    meta = json.loads(js.read_text())
    assert meta["env_info"]["env_kwargs"]["control_mode"] == mode
    return meta["episodes"]


@pytest.fixture(scope="module", params=ENV_IDS)
def joint_demos(request, tmp_path_factory):
    return collect_demos(
        episodes=2,
        seed=3,
        out_dir=tmp_path_factory.mktemp("joint_demos"),
        env_id=request.param,
        control_mode="pd_joint_pos",
    )


def test_joint_pos_demos_record_joint_targets_and_succeed(joint_demos):
    meta = json.loads(open(joint_demos["json"]).read())
    assert meta["env_info"]["env_kwargs"]["control_mode"] == "pd_joint_pos"
    assert joint_demos["episodes_recorded"] == 2 and all(e["success"] for e in meta["episodes"])
    with h5py.File(joint_demos["h5"]) as f:
        for ep in meta["episodes"]:
            actions = f[f"traj_{ep['episode_id']}"]["actions"][:]
            assert actions.shape == (ep["elapsed_steps"], 7)  # 6 joint angles (rad) + the binary gripper
            assert abs(actions[:, :6]).max() < 2 * math.pi and set(abs(actions[:, 6])) == {1.0}


def test_maniskill_converts_joint_pos_demos_to_joint_delta_pos(joint_demos, tmp_path):
    out = replay(joint_demos["h5"], "-c", "pd_joint_delta_pos", "--save-traj", "--allow-failure", cwd=tmp_path)
    episodes = converted_episodes(out, joint_demos["h5"], "pd_joint_delta_pos")
    assert len(episodes) == 2 and all(e["success"] for e in episodes)


@pytest.mark.parametrize("demos", ENV_IDS[:1], indirect=True)  # the tool demos recorded above, not new ones
def test_maniskill_cannot_convert_tool_demos(demos, tmp_path):
    """Why pd_joint_pos exists: ManiSkill converts only from pd_joint_pos and pd_joint_delta_pos."""
    out = replay(demos["h5"], "-c", "pd_joint_delta_pos", cwd=tmp_path)
    assert out.returncode != 0
    assert (
        "NotImplementedError: Script currently does not support converting pd_ee_delta_tool to pd_joint_delta_pos"
        in out.stderr
    )


def test_unknown_control_mode_is_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="pd_joint_vel"):
        collect_demos(episodes=1, out_dir=tmp_path, control_mode="pd_joint_vel")


@pytest.mark.slow
def test_maniskill_replays_joint_pos_demos(joint_demos, tmp_path):
    out = replay(joint_demos["h5"], cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "2/2=100.00%" in out.stdout + out.stderr


# the conversion matrix from pd_joint_pos, on one task: replayed, or refused by the env (a mode our agent lacks)
CONVERSIONS = {
    "pd_joint_delta_pos": None,
    "pd_ee_delta_pose": None,
    "pd_joint_target_delta_pos": "pd_joint_target_delta_pos not in supported modes",
    "pd_joint_vel": "pd_joint_vel not in supported modes",
}


@pytest.mark.slow
@pytest.mark.parametrize("mode", CONVERSIONS)
def test_conversion_matrix_from_joint_pos(mode, tmp_path):
    demos = collect_demos(episodes=2, seed=3, out_dir=tmp_path, env_id=ENV_IDS[0], control_mode="pd_joint_pos")
    out = replay(demos["h5"], "-c", mode, "--save-traj", "--allow-failure", cwd=tmp_path)
    if CONVERSIONS[mode] is None:
        episodes = converted_episodes(out, demos["h5"], mode)
        assert len(episodes) == 2 and all(e["success"] for e in episodes)
    else:
        assert out.returncode != 0 and CONVERSIONS[mode] in out.stderr
