"""Pins every assumption ``maniskill_irb120/maniskill_compat.py`` makes about ManiSkill's internals, so a
ManiSkill upgrade that changes one fails here first (the module mirrors ManiSkill 3.0.1)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import mani_skill
import numpy as np
import pytest
import torch
from mani_skill.agents.controllers.pd_joint_pos import PDJointPosController

import maniskill_irb120  # noqa: F401
from maniskill_irb120 import maniskill_compat as compat

ENV = "TableClearing-IRB120-v1"


def test_mirrored_version_is_installed():
    assert mani_skill.__version__ == compat.MANISKILL_VERSION


def test_maniskill_resets_controllers_with_an_all_true_mask(monkeypatch):
    """Why controllers need the task's record: by the time BaseEnv.reset resets the controllers, the scene's
    ``_reset_mask`` is all-true again, even for a reset of some envs only."""
    env = gym.make(ENV, obs_mode="state")
    env.reset(seed=0)
    u = env.unwrapped
    seen = {}
    original = PDJointPosController.reset

    def spy(self):
        seen["maniskill_mask"] = self.scene._reset_mask.clone()
        seen["recorded"] = getattr(self.scene, compat._MASK_ATTR, None)
        original(self)

    monkeypatch.setattr(PDJointPosController, "reset", spy)
    # the controller's own reset runs inside true_reset_mask, so look at what BaseEnv set before that
    monkeypatch.setattr(compat, "true_reset_mask", _passthrough)
    import maniskill_irb120.robot.controllers as controllers

    monkeypatch.setattr(controllers, "true_reset_mask", _passthrough)
    u.reset(options=dict(env_idx=torch.tensor([0])))
    assert bool(seen["maniskill_mask"].all())
    assert seen["recorded"] is not None and bool(seen["recorded"][0])  # our record of the envs being reset
    env.close()


class _passthrough:
    def __init__(self, scene):
        self.scene = scene

    def __enter__(self):
        return self.scene._reset_mask

    def __exit__(self, *exc):
        return False


def test_maniskill_set_state_dict_drops_controller_state():
    """Why ``restore_controller_state`` exists: BaseEnv.set_state_dict restores actors and articulations only."""
    from mani_skill.envs.sapien_env import BaseEnv

    env = gym.make(ENV, obs_mode="state", control_mode="pd_ee_target_delta_tool")
    env.reset(seed=0)
    u = env.unwrapped
    saved = u.get_state_dict()
    env.step(torch.tensor([[1.0, 1.0, 1.0, 1.0, 1.0]]))
    BaseEnv.set_state_dict(u, saved)  # ManiSkill's own
    arm = u.agent.get_controller_state()["arm"]
    assert not torch.allclose(arm["target_qpos"], saved["controller"]["arm"]["target_qpos"])
    u.set_state_dict(saved)  # ours
    torch.testing.assert_close(
        u.agent.get_controller_state()["arm"]["target_qpos"], saved["controller"]["arm"]["target_qpos"]
    )
    env.close()


def test_direct_drive_targets_equal_maniskills_path():
    env = gym.make(ENV, obs_mode="state")
    env.reset(seed=0)
    arm = env.unwrapped.agent.arm_controller
    targets = arm.qpos + 0.01
    PDJointPosController.set_drive_targets(arm, targets)
    theirs = [float(j._objs[0].drive_target[0]) for j in arm.joints]
    compat.set_drive_targets(arm, targets + 0.01)
    compat.set_drive_targets(arm, targets)
    ours = [float(j._objs[0].drive_target[0]) for j in arm.joints]
    assert ours == theirs
    env.close()


def test_direct_pose_reads_equal_maniskills_path():
    """``raw_pose`` of an actor and of a link (the TCP) is bit for bit ``.pose.raw_pose``, after a step that moved
    both, for every task's objects."""
    for env_id in ("TableClearing-IRB120-v1", "StackCube-IRB120-v1"):
        env = gym.make(env_id, obs_mode="state", render_backend="none")
        env.reset(seed=3)
        env.step(torch.tensor([[0.5, -0.3, -0.8, 0.4, 1.0]]))
        u = env.unwrapped
        for obj in (u.target_object, u.agent.tcp, *u.contacts.objects):
            ours, theirs = compat.raw_pose(obj), obj.pose.raw_pose
            assert ours.dtype == theirs.dtype == torch.float32 and ours.shape == theirs.shape == (1, 7)
            assert torch.equal(ours, theirs), obj.name
        env.close()


def test_sensor_read_back_equals_maniskills_capture():
    """``read_sensor_obs`` after a started capture gives what BaseEnv._get_obs_sensor_data gives."""
    from mani_skill.envs.sapien_env import BaseEnv

    env = gym.make(ENV, obs_mode="rgbd")
    env.reset(seed=0)
    u = env.unwrapped
    u.scene.update_render(update_sensors=True, update_human_render_cameras=False)
    u.capture_sensor_data()
    ours = compat.read_sensor_obs(u)
    theirs = BaseEnv._get_obs_sensor_data(u)
    for k in ("rgb", "depth"):
        assert torch.equal(ours["hand_camera"][k], theirs["hand_camera"][k])
    env.close()


def test_record_episode_info_on_video_writes_a_video(tmp_path):
    """ManiSkill 3.0.1's RecordEpisode(info_on_video=True) calls float() on a (1,)-shaped reward array each step,
    a TypeError from numpy 2.4 on: pyproject pins numpy < 2.4."""
    pytest.importorskip("imageio_ffmpeg", reason="needs imageio[ffmpeg] (dev extras)")
    from mani_skill.utils.wrappers.record import RecordEpisode

    assert np.lib.NumpyVersion(np.__version__) < "2.4.0", (
        f"numpy {np.__version__} is installed but pyproject.toml pins numpy<2.4 (ManiSkill 3.0.1's RecordEpisode "
        "with info_on_video needs it): reinstall with pip install -e '.[dev]'"
    )
    e = gym.make(
        ENV, obs_mode="state", render_mode="rgb_array", human_render_camera_configs=dict(width=128, height=128)
    )
    e = RecordEpisode(
        e, output_dir=str(tmp_path), save_trajectory=False, save_video=True, info_on_video=True, video_fps=20
    )
    e.reset(seed=0)
    for _ in range(3):
        e.step(np.array([0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32))
    e.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert videos and videos[0].stat().st_size > 0


def test_the_physx_gpu_library_is_where_sapien_looks_and_fetches_it():
    """``sapien.physx.enable_gpu`` builds the same folder and archive name (read from its source: calling it
    would fetch ~100 MB on a machine with internet access)."""
    import inspect

    import sapien

    from maniskill_irb120.maniskill_compat import physx_gpu_library

    path, url = physx_gpu_library()
    version = sapien.physx.version()
    assert path.parent == Path.home() / ".sapien" / "physx" / version and path.name == "libPhysXGpu_64.so"
    assert url.endswith(f"/releases/download/{version}/linux-so.zip")
    src = inspect.getsource(sapien.physx.enable_gpu)
    for piece in ('Path.home() / ".sapien" / "physx" / physx_version', '"libPhysXGpu_64.so"', "physx-precompiled"):
        assert piece in src, piece
    assert "/releases/download/{physx_version}/linux-so.zip" in src
