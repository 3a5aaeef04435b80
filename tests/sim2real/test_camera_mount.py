"""Mount correction: a hand camera off its trained mount by a measured offset, its frames reprojected to the
trained mount and the robot's own links drawn in — against frames the sim renders at both mounts."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.sim2real.cameras import (
    overlay_own_view,
    parse_mount,
    reproject_to_mount,
    sim_intrinsics,
)

ENV_ID = "TableClearing-IRB120-v1"
MOUNT = "camera_pos=0.01;-0.01;0.005,camera_rot=3;-3;5"  # the twin's camera-mount shift (benchmarks/sim2real_gap.py)
REPO = Path(__file__).resolve().parents[2]


def hand_frame(randomization: str | None, seed: int):
    """(rgb, depth mm, intrinsics, the robot's own view at that mount) of the hand camera after a reset."""
    env = gym.make(ENV_ID, obs_mode="rgbd", **({"randomization": randomization} if randomization else {}))
    try:
        obs, _ = env.reset(seed=seed)
        cam = obs["sensor_data"]["hand_camera"]
        u = env.unwrapped
        sensor = u.scene.sensors["hand_camera"]
        u.scene.update_render()
        sensor.capture()
        o = sensor.get_obs(rgb=True, depth=True, segmentation=True, position=False)
        ids = torch.cat([link.per_scene_id for link in u.agent.robot.get_links()])
        own = (o["rgb"][0].numpy(), o["depth"][0].numpy(), torch.isin(o["segmentation"][0, ..., 0].long(), ids).numpy())
        k = obs["sensor_param"]["hand_camera"]["intrinsic_cv"][0].numpy()
        return cam["rgb"][0].numpy(), cam["depth"][0].numpy(), k, own
    finally:
        env.close()


def depth_agreement(a: np.ndarray, b: np.ndarray, tol_mm: float = 5.0) -> float:
    return float((np.abs(a[..., 0].astype(np.float64) - b[..., 0]) < tol_mm).mean())


def test_an_offset_mount_s_frame_is_reprojected_to_the_trained_one():
    """The scene's far part comes back from the depth alone; the fingers, 1-3 cm from the lens, do not (a
    centimetre moves them half the image) until the robot's own view draws them in."""
    rgb0, d0, k, own = hand_frame(None, seed=3)
    rgb1, d1, k1, _ = hand_frame(MOUNT, seed=3)
    assert np.allclose(k, sim_intrinsics()) and np.allclose(k1, k)
    pos, rot = parse_mount(MOUNT)
    rgb2, d2 = reproject_to_mount(rgb1, d1, pos, rot, k)
    rgb3, d3 = overlay_own_view(rgb2, d2, own)
    robot = own[2]
    assert 0.05 < robot.mean() < 0.4  # the fingers fill the bottom corners
    assert depth_agreement(d1, d0) < 0.3  # uncorrected: most pixels are off by more than 5 mm
    far = ~robot
    assert np.mean(np.abs(d2[far, 0].astype(float) - d0[far, 0]) < 5) > 0.9  # reprojected: the scene is back
    assert depth_agreement(d2[robot][:, None], d0[robot][:, None]) < 0.5  # ... but not the fingers
    assert depth_agreement(d3, d0) > 0.9  # with the robot drawn in, the whole frame
    assert np.abs(rgb3.astype(float) - rgb0).mean() < 6 < np.abs(rgb1.astype(float) - rgb0).mean()
    assert d3.dtype == d0.dtype and d3.shape == d0.shape and rgb3.dtype == np.uint8


def test_no_offset_is_the_identity_and_holes_are_filled():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (84, 84, 3), dtype=np.uint8)
    depth = rng.integers(150, 300, (84, 84, 1)).astype(np.int16)
    depth[10:14, 20:25] = 0  # no reading there
    out_rgb, out_d = reproject_to_mount(rgb, depth, np.zeros(3), np.zeros(3), sim_intrinsics())
    valid = depth[..., 0] > 0
    assert np.array_equal(out_d[valid], depth[valid]) and np.array_equal(out_rgb[valid], rgb[valid])
    assert (out_d > 0).all()  # the holes took their nearest pixel's reading
    blind = np.zeros_like(depth)  # everything nearer than the sensor's minimum range: nothing to move
    out_rgb, out_d = reproject_to_mount(rgb, blind, np.array([0.01, 0, 0]), np.zeros(3), sim_intrinsics())
    assert np.array_equal(out_rgb, rgb) and not out_d.any()


def test_a_malformed_mount_is_named_before_anything_starts(tmp_path):
    from maniskill_irb120.sim2real.eval import EvalConfig, evaluate

    assert np.allclose(parse_mount(MOUNT)[0], [0.01, -0.01, 0.005]) and np.allclose(parse_mount(MOUNT)[1], [3, -3, 5])
    with pytest.raises(ValueError, match="not a range"):
        parse_mount("camera_pos=0:0.01")
    with pytest.raises(ValueError, match="metres and degrees expected"):
        parse_mount("camera_pos=10;0;0")  # millimetres
    with pytest.raises(ValueError, match="camera_pos and camera_rot only"):
        parse_mount("camera_pos=0.01;0;0,light=0.5")
    with pytest.raises(ValueError, match="give --camera twin or realsense"):
        evaluate(EvalConfig(camera="none", camera_mount=MOUNT, out=tmp_path / "a"))
    with pytest.raises(ValueError, match="use NAME=VALUE"):
        evaluate(EvalConfig(camera_mount="pos=1", out=tmp_path / "b"))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_the_sim_side_keeps_the_trained_mount_and_the_rest_of_the_shift():
    """With --sim-shift and --camera-mount the corrected frames come from the trained mount, so the sim drops the
    mount from the shift and keeps every other field (ranges too), parsed by the randomisation's own parser."""
    from maniskill_irb120.sim2real.eval import EvalConfig, sim_side_shift

    shift = MOUNT + ",depth_noise=2,object_mass=0.5:2,camera_fov=70"
    kept = sim_side_shift(EvalConfig(shift=shift, sim_shift=True, camera_mount=MOUNT))
    assert kept.camera_pos == 0.0 and kept.camera_rot == 0.0
    assert kept.depth_noise == 2.0 and kept.object_mass == (0.5, 2.0) and kept.camera_fov == 70.0
    assert sim_side_shift(EvalConfig(shift=shift, sim_shift=True)).camera_pos == (0.01, -0.01, 0.005)
    assert sim_side_shift(EvalConfig(shift=MOUNT, sim_shift=True, camera_mount=MOUNT)) is None
    assert sim_side_shift(EvalConfig(shift=shift)) is None  # without --sim-shift: the nominal sim
    # command latency: only a fixed-clock robot's steps show it (test_command_latency_delays_the_real_step...)
    lagged = shift + ",latency=0.03"
    assert sim_side_shift(EvalConfig(shift=lagged, sim_shift=True)).latency == 0.0
    assert sim_side_shift(EvalConfig(shift=lagged, sim_shift=True, step_end="period")).latency == 0.03
    assert sim_side_shift(EvalConfig(shift="latency=0.03", sim_shift=True)) is None
    with pytest.raises(ValueError, match="use NAME=VALUE"):
        sim_side_shift(EvalConfig(shift=MOUNT + ",fov=70", sim_shift=True, camera_mount=MOUNT))


def test_the_real_side_sees_the_trained_mount_through_a_corrected_twin_camera(tmp_path):
    """Wired as sim2real-eval wires it: the twin's camera on the offset mount, the correction, and the robot's own
    view rendered by the real agent's sim at the joints the emulated controller reports."""
    pytest.importorskip("lark")
    from maniskill_irb120.sim2real.eval import EvalConfig, _make_real_side, _parse_shift
    from maniskill_irb120.sim2real.policy import load_policy

    policy = str(REPO / "benchmarks/results/policies/dagger-rgbd-bf16-s1-60min.pt")
    depth = {}
    for mount in (None, MOUNT):
        sim_env, _ = load_policy(policy, ENV_ID, "tool_delta")
        cfg = EvalConfig(policy=policy, shift=MOUNT, camera_mount=mount, out=tmp_path)
        real_env, _, twin, emulator = _make_real_side(cfg, sim_env, *_parse_shift(cfg.shift))
        try:
            obs, _ = real_env.reset(seed=11)
            depth[mount] = obs["depth"][0].numpy()
            sim_obs, _ = sim_env.reset(seed=11)
            depth["sim"] = sim_obs["depth"][0].numpy()
        finally:
            real_env.close()
            emulator.stop()
            twin.close()
            sim_env.close()
    assert depth_agreement(depth[None], depth["sim"]) < 0.3
    assert depth_agreement(depth[MOUNT], depth["sim"]) > 0.85
