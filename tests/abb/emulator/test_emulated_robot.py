"""The emulated IRB 120 the controller emulator's RAPID built-ins act on: RAPID's tool conventions give our
TCP, RelTool is pd_ee_delta_tool's step, IK inverts FK, motion takes ABB's axis-speed time plus its ramps,
StopMove holds on the path, world zones stop, and kinematic failures say which. The motion model's own
behaviour (speeddata, look-ahead, robconf) is in test_motion_model.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from maniskill_irb120.abb.emulator.robot import EmulatedIRB120, MotionError, rel_tool
from maniskill_irb120.action import apply_tool_delta
from maniskill_irb120.robot.description import urdf_path
from maniskill_irb120.robot.irb120 import IRB120Metalwork
from maniskill_irb120.robot.kinematics import SerialChain, pose_mm

REST = np.degrees(IRB120Metalwork.keyframes["rest"].qpos[:6])
T_GRIPPER = pose_mm([0, 0, 57], [0.707107, 0, -0.707107, 0])  # the module's tGripper tframe


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


@pytest.fixture(scope="module")
def robot():
    return EmulatedIRB120(REST)


def test_rapid_tool_frame_is_our_tcp(robot):
    chain = SerialChain(urdf_path(), "tcp", dtype=torch.float64)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = REST + rng.uniform(-30, 30, 6)
        ours = chain.forward_kinematics(torch.as_tensor(np.radians(q))[None])[0].numpy()
        np.testing.assert_allclose(robot.tool_pose(q, T_GRIPPER), ours, atol=2e-6)
    # ABB's tool0 at the zero pose: flange at (374, 0, 630) mm, z along base +x
    t0 = robot.tool0(np.zeros(6))
    np.testing.assert_allclose(t0[:3, 3] * 1000, [374.0, 0.0, 630.6], atol=0.1)
    np.testing.assert_allclose(t0[:3, 2], [1, 0, 0], atol=1e-9)


def test_rel_tool_is_the_sims_tool_step(robot):
    rng = np.random.default_rng(1)
    for _ in range(20):
        start = robot.tool_pose(REST + rng.uniform(-20, 20, 6), T_GRIPPER)
        d, rot = rng.uniform(-10, 10, 3), rng.uniform(-10, 10)
        ours = apply_tool_delta(np, start[None], np.r_[d / 1000, math.radians(rot)][None])[0]
        np.testing.assert_allclose(rel_tool(start, *d, rx=rot), ours, atol=1e-12)


def test_solve_inverts_the_tool_pose_and_names_failures(robot):
    q = REST + np.array([10.0, -5.0, 8.0, 20.0, -15.0, 30.0])
    np.testing.assert_allclose(robot.solve(robot.tool_pose(q, T_GRIPPER), T_GRIPPER, REST), q, atol=1e-6)
    far = robot.tool_pose(REST, T_GRIPPER)
    far[:3, 3] = [1.5, 0.0, 0.3]
    with pytest.raises(MotionError) as e:
        robot.solve(far, T_GRIPPER, REST)
    assert e.value.kind == "reach"
    with pytest.raises(MotionError) as e:
        robot.move(REST + [200.0, 0, 0, 0, 0, 0])
    assert e.value.kind == "joint_limit"


def test_motion_takes_axis_speed_time_plus_its_ramps_and_stop_holds_on_the_path():
    """Changed with the motion model: a segment now accelerates and decelerates (it took exactly its axis-speed
    time before), and StopMove decelerates along the path instead of freezing."""
    clock = FakeClock()
    robot = EmulatedIRB120(REST, clock=clock)
    robot.max_tcp_speed_mm_s = None  # auto: axis 1 alone limits
    robot.move(REST + [10.0, 0, 0, 0, 0, 0])  # axis 1 at 250 deg/s: 40 ms at speed, longer with its ramps
    seg = robot.queue[0]
    robot.joints()
    duration = seg.t_end
    assert duration == pytest.approx(1 / seg.v + seg.v / seg.a if seg.v**2 <= seg.a else 2 / math.sqrt(seg.a))
    assert 0.04 < duration < 0.2
    clock.t = duration / 2
    np.testing.assert_allclose(robot.joints()[0], REST[0] + 5.0, atol=1e-9)  # a symmetric profile
    clock.t = duration / 4
    at_call = robot.joints()[0]
    assert robot.busy()
    robot.stop()
    clock.t += 0.2
    stopped_at = robot.joints()[0]
    assert at_call < stopped_at < REST[0] + 10.0 and not robot.busy()  # on the path, some way after the call
    clock.t += 0.5
    assert robot.joints()[0] == stopped_at  # held
    robot.start()
    clock.t += 1.0
    np.testing.assert_allclose(robot.joints()[0], REST[0] + 10.0, atol=1e-9)  # the rest of the path
    assert not robot.busy()
    robot.move(REST, v_tcp=10.0)  # a slow speeddata wins over the axis speed
    clock.t += 0.5
    moving = robot.joints()[0]
    assert REST[0] < moving < REST[0] + 10.0
    robot.stop()
    clock.t += 0.5
    robot.clear_path()
    robot.start()
    here = robot.joints()[0]
    clock.t += 5.0
    np.testing.assert_allclose(robot.joints()[0], here, atol=1e-12)  # the cleared path never runs


def test_world_zone_stops_the_robot_inside_when_it_gets_there():
    """Changed with the motion model: the violation is found when the robot reaches the boundary, not when the
    move is planned; the robot stops there and ``motion_error`` says why."""
    clock = FakeClock()
    robot = EmulatedIRB120(REST, clock=clock)
    p = robot.tool_pose(REST, T_GRIPPER)[:3, 3]
    robot.zone = (p - 0.05, p + 0.05)
    robot.zone_tool = T_GRIPPER
    down = robot.solve(rel_tool(robot.tool_pose(REST, T_GRIPPER), 100.0, 0, 0), T_GRIPPER, REST)  # 10 cm down
    robot.move(down)
    assert robot.motion_error is None and not robot.zone_violation  # planned without complaint
    clock.t = 10.0
    end = robot.tool_pose(robot.joints(), T_GRIPPER)[:3, 3]
    assert robot.zone_violation and robot.motion_error.kind == "world_zone"
    assert np.all(end >= p - 0.05) and np.all(end <= p + 0.05)
    assert end[2] < p[2] - 0.03  # it did move, up to the boundary
    assert not robot.busy() and not robot.queue
