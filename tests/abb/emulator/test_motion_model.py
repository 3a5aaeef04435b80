"""The emulated IRB 120's motion model (robot.py, motion.py): speeddata and the operating mode's TCP cap set a
move's speed, segments accelerate and decelerate, the look-ahead decides fly-by corners (50024 when a point
turns into a stop point), StopMove stops on the path, errors met while moving stop the robot where they are, and
robconf is ABB's confdata, honoured by CalcJointT. All on a fake clock: nothing here sleeps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from maniskill_irb120.abb.emulator.motion import TCP_ACCEL_MM_S2, MotionError
from maniskill_irb120.abb.emulator.robot import EmulatedIRB120, interpolate_pose, rel_tool
from maniskill_irb120.robot.irb120 import IRB120Metalwork
from maniskill_irb120.robot.kinematics import pose_mm

REST = np.degrees(IRB120Metalwork.keyframes["rest"].qpos[:6])
T_GRIPPER = pose_mm([0, 0, 57], [0.707107, 0, -0.707107, 0])  # the module's tGripper tframe
V_FULL = 250.0  # the server's vFull: 250 mm/s, 250 deg/s


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def new_robot() -> tuple[EmulatedIRB120, FakeClock]:
    clock = FakeClock()
    return EmulatedIRB120(REST, clock=clock), clock


def move_l(robot: EmulatedIRB120, dx=0.0, dy=0.0, dz=0.0, rx=0.0, flyby=True, v=V_FULL) -> None:
    """What the server's ToolStep and the MoveL built-in do: a line in the tool frame, IK every millimetre."""
    here = robot.tool_pose(robot.path_end(), T_GRIPPER)
    target = rel_tool(here, dx, dy, dz, rx)
    q1 = robot.solve(target, T_GRIPPER, robot.path_end())
    n = max(2, math.ceil(max(abs(dx), abs(dy), abs(dz), abs(rx))))
    via, ok = robot.solve_line(
        np.stack([interpolate_pose(here, target, s) for s in np.arange(1, n) / n]), T_GRIPPER, q1
    )
    assert ok.all()
    robot.move(q1, via, T_GRIPPER, v, v, flyby, robot.clock())


def tcp(robot: EmulatedIRB120) -> np.ndarray:
    return robot.tool_pose(robot.joints(), T_GRIPPER)[:3, 3] * 1000


def trace(robot: EmulatedIRB120, clock: FakeClock, until: float, dt: float = 0.0005) -> np.ndarray:
    """(t, x, y, z) of the TCP (mm) every ``dt`` until ``until``."""
    rows = []
    while clock.t < until:
        rows.append([clock.t, *tcp(robot)])
        clock.t += dt
    return np.array(rows)


def speeds(rows: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(rows[:, 1:], axis=0), axis=1) / np.diff(rows[:, 0])


# ------------------------------------------------------------------ speeddata, the operating mode, acceleration
def test_a_fine_step_ramps_up_and_down_within_the_tcp_acceleration():
    robot, clock = new_robot()
    start = tcp(robot)
    move_l(robot, dy=10.0, flyby=False)
    rows = trace(robot, clock, 0.1)
    v = speeds(rows)
    assert v.max() == pytest.approx(V_FULL, rel=0.02)  # the programmed speed, reached
    acc = np.abs(np.diff(v)) / 0.0005
    assert acc.max() < TCP_ACCEL_MM_S2 * 1.05  # never faster than the estimate
    # stop to stop: 10 mm at 250 mm/s is 40 ms, plus one ramp time (250 mm/s / 14.3 m/s² = 17.5 ms)
    done = rows[np.argmax(np.linalg.norm(rows[:, 1:] - rows[-1, 1:], axis=1) < 1e-6), 0]
    assert done == pytest.approx(0.04 + V_FULL / TCP_ACCEL_MM_S2, abs=0.001)
    np.testing.assert_allclose(np.linalg.norm(rows[-1, 1:] - start), 10.0, atol=1e-6)


def test_manual_reduced_speed_caps_the_tcp_and_speeddata_slows_move_abs_j():
    """MoveAbsJ's speeddata holds for the TCP (ABB, MoveAbsJ); manual reduced speed caps the TCP at 250 mm/s
    whatever is programmed; in auto (cap None) a joint move runs at the axis speeds."""
    q = REST + [10.0, 0, 0, 0, 0, 0]  # axis 1: the TCP swings ~60 mm
    durations, swing = {}, 0.0
    for name, cap, v_tcp in (("auto", None, 5000.0), ("reduced", 250.0, 5000.0), ("slow", None, 50.0)):
        robot, clock = new_robot()
        robot.max_tcp_speed_mm_s = cap
        robot.move(q, tframe=T_GRIPPER, v_tcp=v_tcp, v_ori=1000.0)
        rows = trace(robot, clock, 3.0, dt=0.001)
        durations[name] = rows[np.argmax(np.abs(rows[:, 1:] - rows[-1, 1:]).max(1) < 1e-9), 0]
        swing = np.linalg.norm(np.diff(rows[:, 1:], axis=0), axis=1).sum()
        if cap is not None:
            assert speeds(rows).max() <= cap * 1.01
    assert durations["auto"] < 0.2  # axis 1 at 250 deg/s: 40 ms plus its ramps
    assert durations["reduced"] > swing / 250.0
    assert durations["slow"] > swing / 50.0


def test_reorientation_speed_limits_a_turn_in_place():
    robot, clock = new_robot()
    move_l(robot, rx=10.0, flyby=False, v=25.0)  # 10 deg at 25 deg/s: 0.4 s
    assert robot.queue[0].v == pytest.approx(1 / 0.4, rel=0.01)


def test_speed_scale_stretches_every_time_exactly():
    ends = []
    for scale in (1.0, 0.5):
        robot, clock = new_robot()
        robot.speed_scale = scale
        move_l(robot, dz=10.0, flyby=False)
        robot.joints()
        ends.append(robot.queue[0].t_end)
    assert ends[1] == pytest.approx(2 * ends[0])


# ------------------------------------------------------------------ the look-ahead rule
def test_a_fly_by_point_blends_when_the_next_move_comes_in_time():
    robot, clock = new_robot()
    move_l(robot, dy=10.0)
    move_l(robot, dy=10.0)
    move_l(robot, dy=10.0, flyby=False)
    rows = trace(robot, clock, 0.2)
    v = speeds(rows)
    cruising = (rows[1:, 0] > 0.03) & (rows[1:, 0] < 0.09)  # both corners lie in here
    assert v[cruising].min() > 0.97 * V_FULL  # no slowing down at the corners
    assert robot.events == []
    assert rows[-1, 0] > 0.04 * 3 + V_FULL / TCP_ACCEL_MM_S2  # three steps at speed, one ramp


def test_a_late_next_move_turns_the_point_into_a_stop_point_and_logs_50024():
    robot, clock = new_robot()
    move_l(robot, dy=10.0)
    trace(robot, clock, 0.045)  # past the point at which the deceleration had to begin
    assert [e[:2] for e in robot.events] == [(50024, "Corner path failure")]
    # from rest: 17.5 ms up to speed, 22.5 ms at speed, then the deceleration was due
    assert robot.events[0][3] == pytest.approx(0.04, abs=1e-3)
    move_l(robot, dy=10.0, flyby=False)
    rows = trace(robot, clock, 0.2)
    v = speeds(rows)
    around = (rows[1:, 0] > 0.05) & (rows[1:, 0] < 0.065)
    assert v[around].min() < 0.02 * V_FULL  # it came to a stop at the first point
    fine_robot, fine_clock = new_robot()
    move_l(fine_robot, dy=10.0, flyby=False)
    trace(fine_robot, fine_clock, 0.1)
    assert fine_robot.events == []  # a fine point is a stop point by design: no event


def test_the_instruction_counts_from_when_it_was_reached_not_when_its_ik_was_done():
    robot, clock = new_robot()
    move_l(robot, dy=10.0)
    clock.t = 0.030  # just before the deadline
    with robot.planning(clock.t):
        clock.t = 0.034  # the emulator's IK took 4 ms and crossed the deadline
        robot.joints()
        move_l(robot, dy=10.0, flyby=False)
    trace(robot, clock, 0.2)
    assert robot.events == []


# ------------------------------------------------------------------ StopMove, StartMove, ClearPath
@pytest.mark.parametrize("quick", [False, True])
def test_stop_move_decelerates_on_the_path_and_start_move_finishes_it(quick):
    robot, clock = new_robot()
    start = tcp(robot)
    move_l(robot, dy=40.0, flyby=False)  # 160 ms at speed
    trace(robot, clock, 0.08)
    at_call = tcp(robot)
    robot.stop(quick=quick)
    trace(robot, clock, 0.2)
    held = tcp(robot)
    travelled = np.linalg.norm(held - at_call)
    ramp = V_FULL**2 / (2 * TCP_ACCEL_MM_S2)  # 2.2 mm at the path deceleration
    assert travelled == pytest.approx(ramp / (2.0 if quick else 1.0), rel=0.02)
    direction = (held - start) / np.linalg.norm(held - start)
    np.testing.assert_allclose(direction, (at_call - start) / np.linalg.norm(at_call - start), atol=1e-4)  # on it
    assert not robot.busy()
    robot.start()
    trace(robot, clock, 0.5)
    np.testing.assert_allclose(np.linalg.norm(tcp(robot) - start), 40.0, atol=1e-6)


def test_stop_move_then_clear_path_drops_the_rest():
    robot, clock = new_robot()
    for _ in range(3):
        move_l(robot, dy=10.0)
    trace(robot, clock, 0.05)
    robot.stop()
    trace(robot, clock, 0.1)
    robot.clear_path()
    robot.start()
    held = tcp(robot)
    trace(robot, clock, 0.5)
    np.testing.assert_allclose(tcp(robot), held, atol=1e-9)
    assert not robot.queue and not robot.busy()


# ------------------------------------------------------------------ errors met while moving
def test_a_world_zone_is_met_when_the_robot_gets_there():
    robot, clock = new_robot()
    p = tcp(robot) / 1000
    robot.zone, robot.zone_tool = (p - 0.005, p + 0.05), T_GRIPPER  # 5 mm below the TCP
    move_l(robot, dx=20.0, flyby=False)  # down, along the tool's approach axis
    assert robot.motion_error is None  # planned without complaint
    trace(robot, clock, 0.02)
    assert robot.motion_error is None  # not there yet
    trace(robot, clock, 0.2)
    assert robot.motion_error is not None and robot.motion_error.kind == "world_zone"
    assert tcp(robot)[2] >= (p[2] - 0.005) * 1000 - 1e-6
    assert not robot.queue


# ------------------------------------------------------------------ robconf
def test_robconf_is_abbs_confdata():
    robot, _ = new_robot()
    assert robot.robconf(REST) == (0, 0, 0, 0)  # the sim's rest pose: axes 1, 4, 6 at 0, a standard config
    assert robot.robconf(REST + [-0.1, 0, 0, -95.0, 0, 185.0]) == (-1, -2, 2, 0)  # floor(angle / 90)
    assert robot.robconf([0, 0, 0, 0, -30, 0])[3] == 1  # axis 5 negative
    assert robot.robconf([0, 30, -85, 0, 30, 0])[3] == 2  # axis 3 past the stretched elbow (-77 deg)
    assert robot.robconf([0, -100, 60, 0, 30, 0])[3] == 4  # the wrist centre behind axis 1


def test_calc_joint_t_honours_robconf():
    robot, _ = new_robot()
    rng = np.random.default_rng(0)
    for _ in range(30):
        q = REST + rng.uniform(-60, 60, 6) * [1, 0.5, 0.5, 1, 0.5, 2]
        pose = robot.tool_pose(q, T_GRIPPER)
        np.testing.assert_allclose(robot.solve_conf(pose, T_GRIPPER, robot.robconf(q)), q, atol=1e-6)
    q = REST + [0, 0, 0, 30, 0, 0]
    flipped = robot.solve_conf(robot.tool_pose(q, T_GRIPPER), T_GRIPPER, (0, -2, -2, 1))  # the other wrist
    np.testing.assert_allclose(robot.tool_pose(flipped, T_GRIPPER), robot.tool_pose(q, T_GRIPPER), atol=1e-9)
    assert flipped[4] < 0 and robot.robconf(flipped) == (0, -2, -2, 1)
    with pytest.raises(MotionError):  # behind axis 1: beyond axis 1's ±165 deg here
        robot.solve_conf(robot.tool_pose(REST, T_GRIPPER), T_GRIPPER, (0, 0, 0, 4))


def test_tool_steps_from_rest_across_quadrant_boundaries():
    """The server's ToolStep: CRobT (robconf of where the robot is), RelTool (keeps it), CalcJointT (honours
    it). REST has axes 1, 4 and 6 at exactly 0: half of all steps cross into quadrant -1. With the nearest-turn
    reading CalcJointT finds the step's own solution; a controller that held the quadrant strictly would refuse
    them (what quadrant_tolerance_deg = 0 shows)."""
    robot, _ = new_robot()
    here = robot.tool_pose(REST, T_GRIPPER)
    conf = robot.robconf(REST)
    crossing = 0
    for d in ([0, 5, 0, 0], [0, -5, 0, 0], [0, 0, 5, 3], [5, 0, 0, -3], [0, 3, -3, 5]):
        target = rel_tool(here, *d[:3], d[3])
        q = robot.solve(target, T_GRIPPER, REST)
        np.testing.assert_allclose(robot.solve_conf(target, T_GRIPPER, conf), q, atol=1e-6)
        if robot.robconf(q) != conf:
            crossing += 1
            robot.quadrant_tolerance_deg = 0.0
            with pytest.raises(MotionError):
                robot.solve_conf(target, T_GRIPPER, conf)
            robot.quadrant_tolerance_deg = None
    assert crossing >= 2


# ------------------------------------------------------------------ streaming: fine vs z1 (docs/real_robot.md)
def stream(period_s: float, steps: int = 20, step_mm: float = 10.0, flyby: bool = True) -> dict:
    """A PC streaming ``steps`` MoveL steps of ``step_mm`` at v250 through the server: it sends a step every
    ``period_s`` at the earliest, and the server answers (so the PC may send the next) once the MoveL has
    returned, i.e. the move is planned (fly-by: one segment of look-ahead; fine: the robot at the point).
    Returns the time the robot took, its mean TCP speed and the 50024 events."""
    robot, clock = new_robot()
    start, dt = tcp(robot), 0.0005
    planned = (lambda: len(robot.queue) <= 1) if flyby else (lambda: not robot.queue)
    for _ in range(steps):
        move_l(robot, dy=step_mm, flyby=flyby)
        next_send = clock.t + period_s
        while clock.t < next_send or not planned():
            clock.t += dt
            robot.joints()
    while robot.busy():
        clock.t += dt
    travelled = np.linalg.norm(tcp(robot) - start)
    return {
        "time_s": clock.t,
        "mean_mm_s": travelled / clock.t,
        "step_s": clock.t / steps,
        "corner_path_failures": sum(e[0] == 50024 for e in robot.events),
    }


def test_streaming_fine_vs_z1():
    """10 mm steps at v250: z1 with a PC that is always a step ahead blends at the full 250 mm/s (40 ms a
    step); a PC sending a step every 50 ms is late for most corners: they turn into stop points (50024) with
    their own ramps; fine stops at every point (40 ms + one 17.5 ms ramp a step, no event)."""
    ahead = stream(period_s=0.0)
    late = stream(period_s=0.05)
    fine = stream(period_s=0.0, flyby=False)
    assert ahead["corner_path_failures"] <= 1 and ahead["mean_mm_s"] > 0.95 * V_FULL * 20 * 0.04 / (20 * 0.04 + 0.02)
    assert late["corner_path_failures"] >= 10
    assert fine["corner_path_failures"] == 0
    assert fine["step_s"] == pytest.approx(0.04 + V_FULL / TCP_ACCEL_MM_S2, abs=0.002)
    assert ahead["mean_mm_s"] > late["mean_mm_s"] > fine["mean_mm_s"]
