"""The 84x84 RGB-D hand camera: shapes, motion, what it sees, and our one-pass shader against ManiSkill's."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch


def red_pixels(rgb: torch.Tensor) -> int:
    rgb = rgb[0].int()
    return int(((rgb[..., 0] > 120) & (rgb[..., 1] < 60) & (rgb[..., 2] < 60)).sum())


def test_hand_camera_shapes_motion_and_sees_cube(bench):
    env = bench.make(obs_mode="rgbd")
    obs, _ = env.reset(seed=0)
    cam = obs["sensor_data"]["hand_camera"]
    assert cam["rgb"].shape == (1, 84, 84, 3) and cam["rgb"].dtype == torch.uint8
    assert cam["depth"].shape == (1, 84, 84, 1)
    # looking straight down at the cube from 24 cm: it is in view, near the image centre
    above = red_pixels(cam["rgb"])
    assert above >= 9  # a 2 cm cube seen from 21 cm with a 90 deg, 84 px camera spans ~4x4 px
    ys, xs = torch.nonzero(cam["rgb"][0, ..., 0].int() - cam["rgb"][0, ..., 1].int() > 100, as_tuple=True)
    assert abs(xs.float().mean().item() - 42) < 12
    depth_mm = cam["depth"][0, ys, xs, 0].float().median().item()
    assert 150 < depth_mm < 300  # cube top ~21 cm below the camera eye
    first_depth = cam["depth"][0].float().median().item()
    for _ in range(35):  # 35 cm sideways: the cube leaves the ~56 cm wide view of the floor
        obs, *_ = env.step(np.array([0, 1, 0, 0, 1], dtype=np.float32))
    for _ in range(6):  # descend 6 cm: the floor comes closer
        obs, *_ = env.step(np.array([1, 0, 0, 0, 1], dtype=np.float32))
    rgb, depth = obs["sensor_data"]["hand_camera"]["rgb"], obs["sensor_data"]["hand_camera"]["depth"]
    assert red_pixels(rgb) < above / 3
    assert depth[0].float().median().item() < first_depth - 40


def test_forward_shader_renders_what_minimal_renders():
    """The one-pass sensor shader is a speed-up, not a different look: along a random walk of the
    arm, RGB and depth match ManiSkill's two-pass ``minimal`` pack."""
    from maniskill_irb120.robot.shaders import sensor_shader_config

    envs = [
        gym.make("TableClearing-IRB120-v1", obs_mode="rgbd"),
        gym.make(
            "TableClearing-IRB120-v1", obs_mode="rgbd", sensor_configs=dict(hand_camera=dict(shader_pack="minimal"))
        ),
    ]
    assert envs[0].unwrapped._sensors["hand_camera"].config.shader_pack.endswith("rgbd_forward")
    assert envs[1].unwrapped._sensors["hand_camera"].config.shader_pack == "minimal"
    obs = [e.reset(seed=3)[0] for e in envs]
    rng = np.random.default_rng(3)
    for step in range(40):
        if step % 8 == 0:
            (fw, mn) = [o["sensor_data"]["hand_camera"] for o in obs]
            assert fw["rgb"].dtype == torch.uint8 and fw["depth"].dtype == torch.int16
            diff = (fw["rgb"].int() - mn["rgb"].int()).abs()
            assert float((diff > 2).float().mean()) < 0.01, f"step {step}: {int(diff.max())} max RGB difference"
            assert torch.equal(fw["depth"], mn["depth"])
        a = rng.uniform(-1, 1, 5).astype(np.float32)
        obs = [e.step(a)[0] for e in envs]
    for e in envs:
        e.close()
    with pytest.raises(ValueError, match="unknown sensor shader"):
        sensor_shader_config("phong")
