"""The operating-mode gate of the shipped RAPID server, on the controller emulator. ABB's ``OpMode()`` (RAPID
Instructions, Functions and Data types: OpMode) returns OP_AUTO, OP_MAN_PROG (manual reduced speed, TCP at most
250 mm/s, the operator holding the enabling device) or OP_MAN_TEST (manual full speed) (docs/reference.md,
ABB section). The issue's finding: nothing read it, so in automatic mode a learned policy ran unattended. The server
now moves only in manual reduced speed unless ALLOW_AUTO is set deliberately; STATE and STOP always work. Also:
zero-length tool steps queue no motion, and a client whose controller stops answering after a motion command is
told to check the pendant."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")

from maniskill_irb120.abb.client import ABBRobot, ControllerRefused, ControllerStopped  # noqa: E402
from maniskill_irb120.abb.emulator.controller import ControllerEmulator, shipped_module  # noqa: E402
from maniskill_irb120.abb.protocol import ErrorCode, Status, ToolStep  # noqa: E402

STEP = [0.5, 0.0, 0.0, 0.0, 1.0]  # half a step along the tool's x axis, gripper open


@pytest.fixture
def emulator():
    emus = []

    def start(**kwargs):
        emu = ControllerEmulator("tcp", **kwargs)
        emus.append(emu)
        return emu, emu.start()

    yield start
    for emu in emus:
        emu.stop()
        assert emu.error is None, emu.error


@pytest.mark.parametrize("mode", ["auto", "manual_full"])
def test_motion_is_refused_outside_manual_reduced_speed(emulator, mode):
    emu, url = emulator(op_mode=mode)
    with ABBRobot.connect(url, timeout=1.0) as robot:
        before = robot.state()
        assert before.error == ErrorCode.OK  # STATE always answers
        for command in (
            lambda: robot.move_tool(STEP),
            lambda: robot.move_joints(np.asarray(before.joints) + np.radians([2.0, 0, 0, 0, 0, 0])),
            lambda: robot.set_gripper(False),
        ):
            with pytest.raises(ControllerRefused, match="not in manual reduced speed") as e:
                command()
            assert e.value.state.error == ErrorCode.OPERATING_MODE
        time.sleep(0.1)
        after = robot.state()
        assert robot.stop().error == ErrorCode.OK  # STOP always works
    assert emu.moves == 0 and emu.signals["doGripperOpen"] == 1
    np.testing.assert_allclose(after.joints, before.joints, atol=1e-9)


def test_manual_reduced_speed_moves_and_the_key_switch_is_read_every_command(emulator):
    emu, url = emulator()  # the default: manual reduced speed
    with ABBRobot.connect(url, timeout=1.0) as robot:
        robot.move_tool(STEP)
        assert emu.moves == 1
        emu.op_mode = "auto"  # the key switch turns mid-session
        with pytest.raises(ControllerRefused, match="ALLOW_AUTO"):
            robot.move_tool(STEP)
        assert emu.moves == 1
        emu.op_mode = "manual_reduced"
        robot.move_tool(STEP)
        assert emu.moves == 2


def test_allow_auto_set_deliberately_moves_in_auto(emulator, tmp_path):
    core = shipped_module().read_text()
    assert core.count("LOCAL CONST bool ALLOW_AUTO := FALSE;") == 1
    copy = tmp_path / "IRB120Server.mod"
    copy.write_text(core.replace("ALLOW_AUTO := FALSE;", "ALLOW_AUTO := TRUE;"))
    emu, url = emulator(rapid=copy, op_mode="auto")
    with ABBRobot.connect(url, timeout=1.0) as robot:
        robot.move_tool(STEP)
    assert emu.moves == 1


def test_speed_percent_slows_every_step(emulator, tmp_path):
    """SPEED_PERCENT scales the step's speed data (a first run's 50 %): a full 10 mm step at 125 mm/s plans 89 ms
    with its ramps (80 ms of it the speed's), a full-speed step 57 ms. The plan is read off the emulator's own clock:
    timing the reply against the wall clock failed on a loaded host, where the reply came late (32 ms left)."""
    core = shipped_module().read_text()
    assert core.count("LOCAL CONST num SPEED_PERCENT := 100;") == 1
    copy = tmp_path / "IRB120Server.mod"
    copy.write_text(core.replace("SPEED_PERCENT := 100;", "SPEED_PERCENT := 50;"))
    emu, url = emulator(rapid=copy)
    segments = []  # the motion the emulator planned, timed on its own clock: no wall-clock race on a loaded host
    plan = emu.robot._segment
    emu.robot._segment = lambda *a: segments.append(plan(*a)) or segments[-1]
    with ABBRobot.connect(url, timeout=1.0) as robot:
        t0 = time.monotonic()
        robot.move_tool([1.0, 0.0, 0.0, 0.0, 1.0])
        while robot.state().status == Status.MOVING:
            time.sleep(0.005)
        took = time.monotonic() - t0
    assert emu.interp.get("vStep").v_tcp == pytest.approx(125.0)
    (seg,) = segments
    planned = seg.t_end - seg.phases[0].t0
    assert 0.08 <= planned < 0.12  # 10 mm at 125 mm/s, with its ramps; a full-speed step plans 57 ms
    assert took >= planned  # from before the command to the robot at rest: the motion, plus the link's delays


def test_a_zero_length_step_queues_no_motion(emulator):
    emu, url = emulator()
    with ABBRobot.connect(url, timeout=1.0) as robot:
        before = robot.state()
        state = robot.move_tool([0.0, 0.0, 0.0, 0.0, -1.0])  # nothing to move; close the gripper
        assert state.error == ErrorCode.OK and not state.gripper_open
        robot.check_envelope = False
        assert robot._request(ToolStep(0.0, 0.0, 0.0, 0.0)).error == ErrorCode.OK  # gripper unchanged (None)
    assert emu.moves == 0 and emu.signals["doGripperOpen"] == 0
    np.testing.assert_allclose(state.joints, before.joints, atol=1e-9)


def test_a_controller_that_stops_mid_session_says_check_the_pendant(emulator):
    emu, url = emulator()
    robot = ABBRobot.connect(url, timeout=0.1, retries=1)
    robot.move_tool(STEP)
    emu.interp.request_stop()  # the program stops (the pendant's stop button, an error): nothing answers
    emu.thread.join(2)
    with pytest.raises(ControllerStopped, match="check the pendant") as e:
        robot.move_tool(STEP)
    assert "emergency stop" in str(e.value) and "no valid reply to ToolStep" in str(e.value)
    robot.port.close()
