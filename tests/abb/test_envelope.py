"""The client-side safety envelope: per-step limits, workspace box, reach, joint limits and axis speeds, each
refusal naming its limit; accepted tool steps are the sim controller's steps; random pushing never leaves the box."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.abb.envelope import WORKSPACE_HIGH, WORKSPACE_LOW, Envelope, EnvelopeError
from maniskill_irb120.action import scale_tool_action
from maniskill_irb120.robot.irb120 import IRB120Metalwork

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


# an episode's last pose through the emulator (a learned policy, seed 1003): TCP (0.31, -0.30, 0.45) m at the
# box's corner, wrist turned -207 deg
WRIST_TURNED = np.array([-0.7728, 0.4726, -0.3892, -0.0003, 1.4877, -3.6107])


def test_plan_move_is_a_straight_joint_line_inside_the_box(env_):
    step = env_._max_joint_step * 0.5
    path = env_.plan_move(WRIST_TURNED, REST, step)
    np.testing.assert_array_equal(path[-1], REST)
    moves = np.diff(np.vstack([WRIST_TURNED, path]), axis=0)
    assert np.all(np.abs(moves) <= step + 1e-12)
    np.testing.assert_allclose(moves / moves[:, 5:6], np.tile(moves[0] / moves[0, 5], (len(moves), 1)), atol=1e-9)
    for q in path:
        env_.check_tcp(env_.tcp_pose(q)[:3, 3])
    # what the reset did before: each axis clipped on its own, so the short moves finish first and the path
    # bends; from here it left the box over the top (the refusal that stopped an evaluation)
    now, left = WRIST_TURNED.copy(), False
    while np.abs(REST - now).max() > 1e-9:
        now = now + np.clip(REST - now, -step, step)
        p = env_.tcp_pose(now)[:3, 3]
        left |= bool(np.any(p > np.asarray(WORKSPACE_HIGH) - env_.margin))
    assert left


def test_plan_move_refuses_before_moving(env_):
    flipped = np.array([-0.32, -0.55, 0.8, -2.27, -0.52, -2.94])  # inside the box, the wrist flipped over
    env_.check_tcp(env_.tcp_pose(flipped)[:3, 3])
    with pytest.raises(EnvelopeError, match=r"\(workspace\): the joint line .* waypoint 1 of 17"):
        env_.plan_move(flipped, REST, env_._max_joint_step * 0.5)
    with pytest.raises(EnvelopeError, match="joint_limit"):
        env_.plan_move(REST, REST + np.r_[0, 0, 0, 0, 0, 10.0], env_._max_joint_step)
