"""Teleoperation of a task, recorded as ManiSkill trajectories: driven through a real terminal (tmux send-keys
into ``maniskill-irb120 teleop --device keyboard``), the saved episode is replayed open-loop by ManiSkill's own
replay tool to the same states; recorded in pd_joint_pos, the tool converts it to pd_joint_delta_pos. In-process
sessions with a scripted device check the world frame, save / reset / discard and the file's contents."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from maniskill_irb120.teleop.devices import Command, Scripted
from maniskill_irb120.teleop.sim import Session, TeleopConfig, teleop

REPO = Path(__file__).resolve().parents[2]
ENV_ID = "GraspLift-IRB120-v1"
TMUX = shutil.which("tmux")
UP = Command(translation=(0.0, 0.0, 1.0))
FORWARD = Command(translation=(1.0, 0.0, 0.0))


def replay(h5: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """ManiSkill's replay tool in a fresh interpreter (the json's env id imports this package)."""
    cmd = [sys.executable, "-m", "mani_skill.trajectory.replay_trajectory", "--traj-path", str(h5), *args]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=cwd, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def states(h5: Path, traj: str = "traj_0") -> dict[str, np.ndarray]:
    out = {}

    def keep(name: str, node) -> None:  # visititems stops at the first callback that returns a value
        if isinstance(node, h5py.Dataset):
            out[name] = node[:]

    with h5py.File(h5) as f:
        f[traj]["env_states"].visititems(keep)
    assert out
    return out


class Tmux:
    """A private tmux server (its own socket) with one session running ``command`` in a real terminal."""

    def __init__(self, command: str, cwd: Path):
        self.base = [TMUX, "-L", f"teleop-test-{os.getpid()}"]
        env = dict(os.environ, PYTHONPATH=str(REPO))
        subprocess.run([*self.base, "new-session", "-d", "-s", "t", "-x", "200", "-y", "50", "-c", str(cwd), command],
                       check=True, env=env, timeout=30)  # fmt: skip

    def screen(self) -> str:
        out = subprocess.run([*self.base, "capture-pane", "-p", "-t", "t"], capture_output=True, text=True, timeout=30)
        return out.stdout

    def wait_for(self, text: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in (screen := self.screen()):
                return screen
            time.sleep(0.2)
        raise AssertionError(f"{text!r} never appeared; the terminal shows:\n{self.screen()}")

    def keys(self, *keys: str, gap: float = 0.04) -> None:
        for k in keys:
            subprocess.run([*self.base, "send-keys", "-t", "t", k], check=True, timeout=30)
            time.sleep(gap)

    def kill(self) -> None:
        subprocess.run([*self.base, "kill-server"], capture_output=True, timeout=30)


def teleop_in_tmux(tmp_path: Path, control_mode: str) -> tuple[Path, dict]:
    """Drive ``maniskill-irb120 teleop`` with keys: up, close the gripper, forward, save, quit."""
    done = tmp_path / "exit_code"
    cmd = (
        f"{sys.executable} -m maniskill_irb120 teleop --env-id {ENV_ID} --device keyboard --seed 5 --view none "
        f"--control-mode {control_mode} --out-dir {tmp_path} --name keys; echo $? > {done}"
    )
    tmux = Tmux(cmd, tmp_path)
    try:
        tmux.wait_for("ready:", timeout=60)
        tmux.keys(*["r"] * 8)  # a held key as the terminal sends it: press, then autorepeat
        tmux.keys("Space", gap=0.2)
        tmux.keys(*["w"] * 8)
        tmux.keys("Enter", gap=0.3)
        tmux.wait_for("saved episode 1", timeout=30)
        tmux.keys("q")
        deadline = time.monotonic() + 60
        while not done.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert done.exists() and done.read_text().strip() == "0", tmux.screen()
    finally:
        tmux.kill()
    return tmp_path / "keys.h5", json.loads((tmp_path / "keys.json").read_text())


def check_recorded(h5: Path, meta: dict, control_mode: str) -> np.ndarray:
    assert meta["env_info"]["env_id"] == f"maniskill_irb120:{ENV_ID}"
    assert meta["env_info"]["env_kwargs"]["control_mode"] == control_mode
    (ep,) = meta["episodes"]
    assert ep["episode_seed"] == 5 and ep["success"] is False  # the task's success, in the file
    with h5py.File(h5) as f:
        actions = f["traj_0"]["actions"][:]
        assert f["traj_0"]["success"].shape == (ep["elapsed_steps"],)
    assert set(actions[:, -1]) == {1.0, -1.0}  # the gripper closed by Space, mid-episode
    return actions


@pytest.mark.skipif(TMUX is None, reason="needs tmux (scripts/setup.sh dev installs it)")
def test_keyboard_teleop_in_a_terminal_replays_to_the_same_states(tmp_path):
    h5, meta = teleop_in_tmux(tmp_path, "pd_ee_delta_tool")
    actions = check_recorded(h5, meta, "pd_ee_delta_tool")
    assert (actions[:, 2] != 0).any() and (actions[:, 0] != 0).any()  # up, then forward (both in the tool frame)
    replay(h5, "--save-traj", "--allow-failure", cwd=tmp_path)  # open loop: the recorded actions alone
    replayed = states(h5.with_name("keys.none.pd_ee_delta_tool.physx_cpu.h5"))
    recorded = states(h5)
    assert replayed.keys() == recorded.keys()
    for k in recorded:
        np.testing.assert_allclose(replayed[k], recorded[k], atol=1e-4, err_msg=k)
    robot = recorded["articulations/irb120_metalwork"]
    assert np.abs(robot[-1] - robot[0]).max() > 0.01  # it did move


@pytest.mark.slow
@pytest.mark.skipif(TMUX is None, reason="needs tmux (scripts/setup.sh dev installs it)")
def test_keyboard_teleop_in_joint_pos_is_converted_by_maniskill(tmp_path):
    h5, meta = teleop_in_tmux(tmp_path, "pd_joint_pos")
    check_recorded(h5, meta, "pd_joint_pos")
    replay(h5, "-c", "pd_joint_delta_pos", "--save-traj", "--allow-failure", cwd=tmp_path)
    converted = json.loads(h5.with_name("keys.none.pd_joint_delta_pos.physx_cpu.json").read_text())
    assert converted["env_info"]["env_kwargs"]["control_mode"] == "pd_joint_delta_pos"
    qpos = slice(13, 19)  # root pose (13) then the arm's 6 joints in ManiSkill's articulation state
    end = states(h5)["articulations/irb120_metalwork"][-1, qpos]
    got = states(h5.with_name("keys.none.pd_joint_delta_pos.physx_cpu.h5"))["articulations/irb120_metalwork"]
    np.testing.assert_allclose(got[-1, qpos], end, atol=0.01)


def test_joint_pos_session_records_what_maniskill_converts(tmp_path):
    """The same path without a terminal (a scripted device), so the default suite converts teleop demos."""
    cmds = [UP] * 6 + [Command(gripper_toggle=True)] + [FORWARD] * 6 + [Command(save=True)]
    cfg = TeleopConfig(env_id=ENV_ID, control_mode="pd_joint_pos", out_dir=tmp_path, seed=5, realtime=False)
    res = teleop(cfg, Scripted(cmds), say=lambda _: None)
    assert res["episodes_saved"] == 1
    h5 = Path(res["h5"])
    replay(h5, "-c", "pd_joint_delta_pos", "--save-traj", "--allow-failure", cwd=tmp_path)
    qpos = slice(13, 19)
    end = states(h5)["articulations/irb120_metalwork"][-1, qpos]
    got = states(h5.with_name("teleop.none.pd_joint_delta_pos.physx_cpu.h5"))["articulations/irb120_metalwork"]
    np.testing.assert_allclose(got[-1, qpos], end, atol=0.01)


def test_world_frame_moves_along_world_axes_and_episodes_are_kept_only_when_saved(tmp_path):
    said = []
    cfg = TeleopConfig(env_id=ENV_ID, frame="world", out_dir=tmp_path, seed=2, realtime=False, speed=1.0)
    session = Session(cfg, Scripted([]), say=said.append)
    try:
        agent = session.env.unwrapped.agent
        start = agent.tcp_pose.p[0].clone()
        for _ in range(5):
            session.env.step(session.action(UP))
            session.steps += 1
        moved = agent.tcp_pose.p[0] - start
        assert moved[2] > 0.03 and torch.abs(moved[:2]).max() < 0.005  # straight up, ~1 cm a step
        session.device = Scripted([Command(reset=True), FORWARD, Command(discard=True), FORWARD, Command(save=True)])
        for _ in range(5):
            session.step()
        assert session.seed == 4  # reset kept seed 2, discard moved to 3, save to 4
    finally:
        session.close()
    meta = json.loads((tmp_path / "teleop.json").read_text())
    assert [e["episode_seed"] for e in meta["episodes"]] == [3] and meta["episodes"][0]["elapsed_steps"] == 1
    assert said[-2].startswith("saved episode 1 (seed 3, 1 steps")


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="pd_joint_vel"):
        TeleopConfig(control_mode="pd_joint_vel")
    with pytest.raises(ValueError, match="frame"):
        TeleopConfig(frame="camera")
    with pytest.raises(ValueError, match="speed"):
        TeleopConfig(speed=2.0)
