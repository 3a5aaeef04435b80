"""The tool-frame controller in physics: commanded TCP motion, clipping, unreachable targets, bad
actions, every control mode."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.geometry.rotation_conversions import matrix_to_axis_angle

from maniskill_irb120.robot.irb120 import IRB120Metalwork


@pytest.mark.parametrize("solver", ["closed_form", "dls"])
def test_tool_delta_moves_tcp_as_commanded(bench, solver):
    env = bench.make()
    if solver == "dls":  # what ik_solver="dls" (or a chain without a spherical wrist) gets
        env.unwrapped.agent.arm_controller.ik.method = "dls"
    rng = np.random.default_rng(0)
    for _ in range(8):
        a = np.r_[rng.uniform(-1, 1, 4), 1.0].astype(np.float32)
        t0 = bench.tcp_matrix(env)
        env.step(a)
        for _ in range(5):
            env.step(bench.OPEN)
        rel = torch.linalg.inv(t0) @ bench.tcp_matrix(env)
        np.testing.assert_allclose(rel[:3, 3].numpy(), a[:3] * 0.01, atol=2e-3)
        aa = matrix_to_axis_angle(rel[:3, :3][None])[0].numpy()
        np.testing.assert_allclose(aa, [math.radians(10) * a[3], 0, 0], atol=math.radians(1.0))
        assert not env.unwrapped.agent.ik_unreachable.any()


def test_out_of_range_actions_are_clipped_to_limits(bench):
    env = bench.make()
    t0 = bench.tcp_matrix(env)
    env.step(np.array([5.0, -7.0, 0, 3.0, 1], dtype=np.float32))  # clipped to [1, -1, 0, 1]
    for _ in range(5):
        env.step(bench.OPEN)
    rel = torch.linalg.inv(t0) @ bench.tcp_matrix(env)
    np.testing.assert_allclose(rel[:3, 3].numpy(), [0.01, -0.01, 0], atol=2e-3)
    assert matrix_to_axis_angle(rel[:3, :3][None])[0, 0].item() == pytest.approx(math.radians(10), abs=math.radians(1))


def test_unreachable_target_keeps_last_reachable_and_is_reported(bench):
    env = bench.make()
    agent = env.unwrapped.agent
    for _ in range(60):  # push the TCP backwards (-x, up) far beyond the 0.58 m reach envelope
        env.step(np.array([-1, 0, 0, 0, 1], dtype=np.float32))
        if agent.ik_unreachable.any():
            break
    else:
        pytest.fail("target never became unreachable")
    q_before = agent.robot.get_qpos().clone()
    env.step(np.array([-1, 0, 0, 0, 1], dtype=np.float32))
    assert agent.ik_unreachable.all()
    q = agent.robot.get_qpos()
    assert torch.isfinite(q).all()
    assert (q - q_before).abs().max() < 0.02  # held, not flung towards a bogus solution


@pytest.mark.parametrize(
    "bad, msg",
    [
        (np.array([0, 0, np.nan, 0, 1], dtype=np.float32), "NaN"),
        (np.array([0, 0, np.inf, 0, 1], dtype=np.float32), "NaN or inf"),
        (np.zeros(4, dtype=np.float32), "shape"),
        (np.zeros((2, 5), dtype=np.float32), "shape"),
    ],
)
def test_bad_actions_raise_clear_errors(bench, bad, msg):
    env = bench.make()
    with pytest.raises(ValueError, match=msg):
        env.step(bad)


def test_unknown_control_mode_is_rejected():
    with pytest.raises(Exception, match="pd_nonsense"):
        gym.make("IRB120CubeBench-test", control_mode="pd_nonsense")


@pytest.mark.parametrize(
    "mode", ["pd_ee_delta_tool", "pd_ee_target_delta_tool", "pd_joint_pos", "pd_joint_delta_pos", "pd_ee_delta_pose"]
)
def test_all_control_modes_step(bench, mode):
    env = bench.make(control_mode=mode)
    if mode == "pd_joint_pos":
        a = np.r_[IRB120Metalwork.keyframes["rest"].qpos[:6], 1.0].astype(np.float32)
    else:
        a = np.zeros(env.action_space.shape, dtype=np.float32)
    for _ in range(3):
        env.step(a)
    assert torch.isfinite(env.unwrapped.agent.robot.get_qpos()).all()
    env.close()


def test_tool_action_scaling_is_maniskills_convention():
    """scale_tool_action (shared with the real-robot client) = ManiSkill's clip-and-scale for our limits."""
    from mani_skill.utils import gym_utils

    from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT, scale_tool_action

    a = np.random.default_rng(0).uniform(-1.5, 1.5, (64, 4))
    high = np.array([TOOL_POS_LIMIT] * 3 + [TOOL_ROT_LIMIT])
    theirs = gym_utils.clip_and_scale_action(torch.as_tensor(a), torch.as_tensor(-high), torch.as_tensor(high))
    np.testing.assert_allclose(scale_tool_action(a), theirs.numpy(), atol=1e-12)
    t = torch.as_tensor(a, dtype=torch.float32)
    torch.testing.assert_close(scale_tool_action(t), torch.as_tensor(scale_tool_action(a), dtype=torch.float32))
