"""The client-side safety envelope: per-step limits, workspace box, reach, joint limits and axis speeds, each
refusal naming its limit; accepted tool steps are the sim controller's steps; random pushing never leaves the box."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.agents.irb120 import IRB120Metalwork
from maniskill_irb120.controllers import scale_tool_action
from maniskill_irb120.real.envelope import WORKSPACE_HIGH, WORKSPACE_LOW, Envelope, EnvelopeError

REST = IRB120Metalwork.keyframes["rest"].qpos[:6].astype(np.float64)


@pytest.fixture(scope="module")
def env_():
    return Envelope()


def test_accepted_step_is_the_sim_controllers_step(env_):
    env = gym.make("TableClearing-IRB120-v1", obs_mode="state")
    env.reset(seed=0)
    agent = env.unwrapped.agent
    rng = np.random.default_rng(0)
    for _ in range(10):
        a = rng.uniform(-1.2, 1.2, 5).astype(np.float32)
        q_now = agent.robot.get_qpos()[0, :6].double().numpy()
        agent.set_action(torch.as_tensor(a)[None])  # the sim's pd_ee_delta_tool target for this state
        sim_q = agent.arm_controller._target_qpos[0].double().numpy()
        step = scale_tool_action(a[:4].astype(np.float64))
        q = env_.check_tool_step(q_now, step[:3], step[3])
        np.testing.assert_allclose(q, sim_q, atol=2e-4)
        env.step(a)
    env.close()


@pytest.mark.parametrize(
    "d, rot, limit",
    [
        ((0.011, 0, 0), 0.0, "step"),
        ((0, 0, 0), math.radians(10.5), "step"),
        ((0, float("nan"), 0), 0.0, "step"),
    ],
)
def test_step_limits(env_, d, rot, limit):
    with pytest.raises(EnvelopeError, match=limit) as e:
        env_.check_tool_step(REST, d, rot)
    assert e.value.limit == limit


def test_workspace_floor_refuses_before_the_table(env_):
    q = REST.copy()
    for _ in range(60):  # +x is the approach axis, pointing down at rest
        try:
            q = env_.check_tool_step(q, (0.01, 0, 0), 0.0)
        except EnvelopeError as e:
            assert e.limit == "workspace"
            break
    else:
        raise AssertionError("never refused")
    assert env_.tcp_pose(q)[2, 3] >= WORKSPACE_LOW[2]


def test_joint_limits_and_speed(env_):
    far = REST.copy()
    far[0] = math.radians(170)
    with pytest.raises(EnvelopeError, match="axis 1 target 170.00 deg") as e:
        env_.check_joints(REST, far)
    assert e.value.limit == "joint_limit"
    jump = REST.copy()
    jump[0] += math.radians(20)  # ABB axis 1: 250 deg/s, 12.5 deg per 50 ms
    with pytest.raises(EnvelopeError, match="joint_speed"):
        env_.check_joints(REST, jump)
    small = REST.copy()
    small[0] += math.radians(5)
    np.testing.assert_array_equal(env_.check_joints(REST, small), small)
    with pytest.raises(EnvelopeError, match="6 finite angles"):
        env_.check_joints(REST, [0.0] * 5)


def test_random_pushing_never_leaves_the_box(env_):
    """Sequences of random steps biased outwards: whatever is accepted keeps the TCP inside the box."""
    rng = np.random.default_rng(1)
    low, high = np.asarray(WORKSPACE_LOW), np.asarray(WORKSPACE_HIGH)
    refused = set()
    for _ in range(40):
        q = REST.copy()
        bias = rng.uniform(-1, 1, 4)
        for _ in range(25):
            step = scale_tool_action(np.clip(bias + rng.normal(0, 0.3, 4), -1, 1))
            try:
                q = env_.check_tool_step(q, step[:3], step[3])
            except EnvelopeError as e:
                refused.add(e.limit)
                continue
            p = env_.tcp_pose(q)[:3, 3]
            assert np.all(p >= low - 1e-9) and np.all(p <= high + 1e-9)
    assert "workspace" in refused
