"""The client against the controller emulator running the shipped RAPID module over a pty (serial) and TCP
loopback: state, tool steps that land where the simulator's pd_ee_delta_tool lands, joint moves, the gripper,
and the controller's own checks with the client's envelope turned off (the RAPID side holds alone)."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")

from maniskill_irb120.abb.client import (  # noqa: E402
    ABBRobot,
    ControllerRefused,
    ControllerStopped,
    RobotDisconnected,
    RobotTimeout,
)
from maniskill_irb120.abb.emulator.controller import ControllerEmulator, shipped_module  # noqa: E402
from maniskill_irb120.abb.emulator.rapid import RapidSyntaxError  # noqa: E402
from maniskill_irb120.abb.envelope import WORKSPACE_HIGH, WORKSPACE_LOW, Envelope, EnvelopeError  # noqa: E402
from maniskill_irb120.abb.protocol import ErrorCode, Status, ToolStep, command_frame  # noqa: E402
from maniskill_irb120.action import scale_tool_action  # noqa: E402


def settled(robot: ABBRobot, wait: float = 0.08):
    time.sleep(wait)  # a full step takes 40 ms at the module's speed data
    return robot.state()


@pytest.fixture(params=["serial", "tcp"])
def emulator(request):
    emu = ControllerEmulator(request.param)
    url = emu.start()
    yield emu, url
    emu.stop()
    assert emu.error is None, emu.error


def test_tool_steps_land_where_the_simulator_lands(emulator):
    emu, url = emulator
    envelope = Envelope()
    rng = np.random.default_rng(0)
    with ABBRobot.connect(url, timeout=1.0) as robot:
        state = robot.state()
        assert state.status == Status.IDLE and state.gripper_open
        for _ in range(6):
            a = np.r_[rng.uniform(-1, 1, 4), 1.0]
            step = scale_tool_action(a[:4])
            expect = envelope.tcp_pose(envelope.check_tool_step(state.joints, step[:3], step[3]))  # the sim's IK
            robot.move_tool(a)
            state = settled(robot)
            got = envelope.tcp_pose(state.joints)
            assert np.abs(np.asarray(state.tcp_pos) - expect[:3, 3]).max() < 5e-4  # the reply's TCP, within 0.5 mm
            assert np.abs(got[:3, 3] - expect[:3, 3]).max() < 5e-4
            angle = np.degrees(np.arccos(np.clip((np.trace(got[:3, :3].T @ expect[:3, :3]) - 1) / 2, -1, 1)))
            assert angle < 0.1


def test_joint_moves_and_gripper(emulator):
    emu, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as robot:
        q = np.asarray(robot.state().joints) + np.radians([3.0, -2.0, 2.0, 5.0, -4.0, 8.0])
        robot.move_joints(q, gripper_open=False)
        state = settled(robot, 0.3)  # MoveAbsJ at v250 in manual reduced speed: the TCP's ~25 mm take 121 ms
        np.testing.assert_allclose(state.joints, q, atol=np.radians(0.02))
        assert not state.gripper_open and emu.signals["doGripperOpen"] == 0
        assert robot.set_gripper(True).gripper_open


def test_controller_refuses_alone(emulator):
    """With the client's envelope off, the RAPID module's own checks refuse and nothing moves."""
    emu, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as robot:
        robot.check_envelope = False
        before = robot.state().joints
        with pytest.raises(ControllerRefused, match="per-step limit") as e:
            robot._request(ToolStep(0.02, 0.0, 0.0, 0.0))
        assert e.value.state.error == ErrorCode.STEP_LIMIT
        with pytest.raises(ControllerRefused, match="joint would move"):
            robot.move_joints(np.asarray(before) + np.radians([30.0, 0, 0, 0, 0, 0]))
        emu.signals["doMotorsOn"] = 0
        with pytest.raises(ControllerRefused, match="motors are off"):
            robot.move_tool([0.1, 0, 0, 0, 1])
        emu.signals["doMotorsOn"] = 1
        np.testing.assert_allclose(settled(robot).joints, before, atol=1e-9)


def push_outwards(robot: ABBRobot, emu: ControllerEmulator, sequences: int, steps: int, seed: int) -> set:
    """Random action sequences, each biased in one random direction; after every step the emulated robot's TCP
    (exact, not a reply's quantised joints) must be inside the workspace box. Returns the refusals met (the
    pushing must reach the limits)."""
    low, high = np.asarray(WORKSPACE_LOW), np.asarray(WORKSPACE_HIGH)
    rng = np.random.default_rng(seed)
    refused = set()
    for _ in range(sequences):
        bias = rng.uniform(-1, 1, 4) * [1, 1, 1, 0.3]  # a strong turn would curl the path back inwards
        for _ in range(steps):
            try:
                robot.move_tool(np.r_[np.clip(bias + rng.normal(0, 0.3, 4), -1, 1), 1.0])
            except ControllerRefused as e:
                refused.add(e.state.error.name)
            except EnvelopeError as e:
                refused.add(e.limit)
            p = emu.robot.tool_pose(emu.robot.joints(), emu.robot.zone_tool)[:3, 3]
            assert np.all(p >= low - 1e-4) and np.all(p <= high + 1e-4), p
    return refused


def without_rapid_box(tmp_path):
    """A copy of the core module whose workspace check is opened up to ±10 m; run it without the world-zone module
    (no 608-1, so no world-zone module): the client alone holds."""
    text = shipped_module().read_text()
    text = text.replace("CONST pos WORKSPACE_LOW := [150, -320, 10];", "CONST pos WORKSPACE_LOW := [-1E4, -1E4, -1E4];")
    text = text.replace("CONST pos WORKSPACE_HIGH := [600, 320, 450];", "CONST pos WORKSPACE_HIGH := [1E4, 1E4, 1E4];")
    path = tmp_path / "no_box.mod"
    path.write_text(text)
    return path


@pytest.mark.parametrize("side", ["controller", "client"])
def test_random_outward_pushing_never_leaves_the_box_with_one_side_alone(side, tmp_path):
    alone = side == "client"
    emu = ControllerEmulator(
        "tcp", rapid=without_rapid_box(tmp_path) if alone else None, options=("616-1",) if alone else ("616-1", "608-1")
    )  # the world zone: 608-1
    with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
        robot.check_envelope = side == "client"
        refused = push_outwards(robot, emu, sequences=6, steps=20, seed=1)
    emu.stop()
    assert refused and emu.error is None
    assert ("WORKSPACE" in refused) if side == "controller" else ("workspace" in refused)


@pytest.mark.slow
@pytest.mark.parametrize("side", ["controller", "client"])
def test_thousand_random_sequences_with_one_side_alone(side, tmp_path):
    """The issue's figure: 1000 random sequences pushing outwards, each side alone. The client side holds
    because it checks the step from every corner of the path the controller may still be on."""
    alone = side == "client"
    emu = ControllerEmulator(
        "tcp", rapid=without_rapid_box(tmp_path) if alone else None, options=("616-1",) if alone else ("616-1", "608-1")
    )  # the world zone: 608-1
    with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
        robot.check_envelope = side == "client"
        refused = push_outwards(robot, emu, sequences=1000, steps=4, seed=3)
    emu.stop()
    assert refused and emu.error is None


def test_a_repeated_frame_is_answered_but_not_executed_twice(emulator):
    emu, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as robot:
        start = np.asarray(robot.state().tcp_pos)
        raw = command_frame(ToolStep(0.005, 0.0, 0.0, 0.0), 77).encode()
        for _ in range(3):
            robot.port.write(raw)
            time.sleep(0.1)
        robot.port.reset_input_buffer()
        moved = np.linalg.norm(np.asarray(robot.state().tcp_pos) - start)
        assert moved == pytest.approx(0.005, abs=5e-4)


def test_watchdog_stops_a_silent_pc_mid_motion(tmp_path):
    """A step lasts 40 ms, so the shipped 0.5 s heartbeat can only catch queued motion; a copy of the module
    with a 20 ms heartbeat on a slowed robot shows the mechanism: silence mid-step stops the robot short and
    holds it, the next motion command is refused so the PC learns of it, the one after runs."""
    fast = tmp_path / "fast_watchdog.mod"
    fast.write_text(
        shipped_module().read_text().replace("CONST num HEARTBEAT_S := 0.5;", "CONST num HEARTBEAT_S := 0.02;")
    )
    emu = ControllerEmulator("tcp", rapid=fast, speed_scale=0.3)  # a 133 ms step: silence surely falls within it
    with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
        start = np.asarray(robot.state().tcp_pos)
        robot.move_tool([1.0, 0, 0, 0, 1])
        time.sleep(0.3)  # silent
        state = robot.state()
        assert state.status == Status.HELD
        assert np.linalg.norm(np.asarray(state.tcp_pos) - start) < 0.009  # stopped short of the 10 mm step
        with pytest.raises(ControllerRefused, match="heartbeat"):
            robot.move_tool([0.5, 0, 0, 0, 1])
        assert robot.move_tool([0.5, 0, 0, 0, 1]).error == ErrorCode.OK  # the next command runs
    emu.stop()
    assert emu.error is None


def test_a_pause_after_the_robot_arrived_is_not_a_fault(emulator, slow_clock):
    """MOVING ends when the robot arrives: a PC that pauses longer than the heartbeat between episodes (an
    operator, a scene reset) finds the robot IDLE and its next command runs."""
    emu, url = emulator
    # the robot at a third of wall-clock speed (~90 ms of motion for this half step): at full speed a loaded CI box
    # once sent the reply after the robot had already arrived
    slow_clock(emu.robot)
    with ABBRobot.connect(url, timeout=1.0) as robot:
        assert robot.move_tool([0.5, 0, 0, 0, 1]).status == Status.MOVING
        time.sleep(0.8)
        assert robot.state().status == Status.IDLE
        assert robot.move_tool([0.5, 0, 0, 0, 1]).error == ErrorCode.OK


def test_editing_the_module_changes_the_emulator(tmp_path):
    patched = tmp_path / "server.mod"
    patched.write_text(
        shipped_module().read_text().replace("CONST num STEP_POS_MM := 10;", "CONST num STEP_POS_MM := 5;")
    )
    for path, refused in ((None, False), (patched, True)):
        emu = ControllerEmulator("tcp", rapid=path)
        with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
            robot.check_envelope = False
            if refused:
                with pytest.raises(ControllerRefused, match="per-step limit"):
                    robot.move_tool([0.7, 0, 0, 0, 1])
            else:
                assert robot.move_tool([0.7, 0, 0, 0, 1]).error == ErrorCode.OK
        emu.stop()
    broken = tmp_path / "broken.mod"
    broken.write_text(shipped_module().read_text().replace("ENDWHILE", "ENDWHIL", 1))
    with pytest.raises(RapidSyntaxError, match="line"):
        ControllerEmulator("tcp", rapid=broken)


# --------------------------------------------------------------------------- injected faults (reply numbers: 1 is
# the state read by connect(), 2 the first command after it)
@pytest.mark.parametrize("channel", ["serial", "tcp"])
@pytest.mark.parametrize("fault", ["drop@2", "corrupt@2", "delay@2:400", "dup@2"])
def test_lost_bad_late_or_doubled_replies_run_the_step_once(channel, fault):
    emu = ControllerEmulator(channel, faults=fault)
    with ABBRobot.connect(emu.start(), timeout=0.25) as robot:
        start = np.asarray(robot.state().tcp_pos)
        robot.move_tool([0.5, 0, 0, 0, 1])  # retried where needed, never repeated
        assert robot.state().error == ErrorCode.OK  # a doubled reply does not confuse the next exchange
        assert emu.moves == 1
        assert np.linalg.norm(np.asarray(settled(robot).tcp_pos) - start) == pytest.approx(0.005, abs=5e-4)
    emu.stop()
    assert emu.error is None


def test_disconnect_mid_frame_holds_the_robot_and_a_new_client_gets_in():
    emu = ControllerEmulator("tcp", faults="disconnect@3")
    url = emu.start()
    robot = ABBRobot.connect(url, timeout=0.25, retries=1)
    robot.move_tool([0.5, 0, 0, 0, 1])
    with pytest.raises((RobotTimeout, RobotDisconnected), match="no valid reply|connection to the controller lost"):
        robot.move_tool([0.5, 0, 0, 0, 1])  # half a reply, then the line is dead
    robot.port.close()
    with ABBRobot.connect(url, timeout=1.0) as again:  # the module waits for its peer again
        assert again.state().status == Status.HELD
        assert again.move_tool([0.5, 0, 0, 0, 1]).error == ErrorCode.OK
    emu.stop()
    assert emu.error is None


@pytest.mark.parametrize("fault", ["motors_off@2", "estop@2"])
def test_injected_controller_faults_halt_the_program(fault):
    """``--fault estop@N`` / ``motors_off@N``: as reply N goes out, the program halts as an IRC5's does (an
    emergency stop; the enabling device let go in manual mode): the next command gets no reply, and the client
    says to check the pendant. After the operator's reset and Start, motion waits for a new session."""
    emu = ControllerEmulator("tcp", faults=fault)
    robot = ABBRobot.connect(emu.start(), timeout=0.3, retries=1)
    robot.state()  # reply 2 halts the program
    with pytest.raises(ControllerStopped, match="check the pendant"):
        robot.move_tool([0.5, 0, 0, 0, 1])
    assert emu.moves == 0 and emu.program_state == "stopped" and not emu.motors_on
    if fault.startswith("estop"):
        emu.reset_emergency_stop()
    emu.enabling_device(True)
    emu.press_start()
    robot.hello()
    assert robot.move_tool([0.5, 0, 0, 0, 1]).error == ErrorCode.OK and emu.moves == 1
    robot.close()
    emu.stop()
    assert emu.error is None


def test_bad_fault_spec_is_named():
    with pytest.raises(ValueError, match="fault 'melt@2'"):
        ControllerEmulator("tcp", faults="melt@2")


# --------------------------------------------------------------------------- line speed and latency
def round_trips(slow: ControllerEmulator, fast: ControllerEmulator, n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per tiny tool step, back and forth, on two links taken in turns, n times each.

    Delay a link adds shows in every sample, so lower bounds hold for the fastest. A loaded
    2-core box adds its own delay to every sample too (CI measured 30-50 ms a round trip, and
    it drifts over a second), so comparisons are made on pairs taken back to back, by median.
    """
    times = np.zeros((2, n))
    with ABBRobot.connect(slow.start(), timeout=1.0) as a, ABBRobot.connect(fast.start(), timeout=1.0) as b:
        for i in range(n):
            for k, robot in enumerate((a, b)):
                t0 = time.perf_counter()
                robot.move_tool([0.05 * (-1) ** i, 0, 0, 0, 1])
                times[k, i] = time.perf_counter() - t0
    slow.stop()
    fast.stop()
    return times[0], times[1]


def test_baud_rate_paces_the_pty_like_a_serial_line():
    wire = (15 + 32) * 10 / 9600  # a tool step and its reply, 10 bits a byte
    slow, fast = round_trips(ControllerEmulator("serial", baud=9600), ControllerEmulator("serial", baud=115200))
    assert slow.min() >= wire
    gap = np.median(slow - fast)  # the line speed is what separates them: ~45 ms
    assert wire - 0.02 < gap < wire + 0.03
    with pytest.raises(ValueError, match="serial channel only"):
        ControllerEmulator("tcp", baud=9600)


def test_latency_holds_every_command_back():
    times, reference = round_trips(ControllerEmulator("tcp", latency_ms=60), ControllerEmulator("tcp"))
    assert times.min() >= 0.06
    assert 0.06 - 0.02 < np.median(times - reference) < 0.06 + 0.03
    with pytest.raises(ValueError, match="latency_ms"):
        ControllerEmulator("tcp", latency_ms=float("nan"))


def test_cli_listen_url_sets_the_line_speed(capsys, monkeypatch):
    from maniskill_irb120.abb.emulator import controller as module

    seen = {}

    class Probe(ControllerEmulator):
        def start(self):
            seen.update(baud=self.baud, latency=self.link.latency_s)
            url = super().start()
            self.interp.request_stop()
            return url

    monkeypatch.setattr(module, "ControllerEmulator", Probe)
    assert module.main("serial://pty?baudrate=9600", latency_ms=20) == 0
    assert seen == dict(baud=9600, latency=0.02)
    assert capsys.readouterr().out.splitlines()[0].endswith("?baudrate=9600")


def test_cli_statement_cost_and_pc_address(capsys, monkeypatch):
    """``maniskill-irb120 emulator --statement-cost-us 25 --pc-address 10.0.0.7``: the controller's per-statement
    time and the TCP build's PC_ADDRESS; values that cannot be right are refused by name with exit status 2."""
    from maniskill_irb120.abb.emulator import controller as module
    from maniskill_irb120.cli import main

    seen = {}

    class Probe(ControllerEmulator):
        def start(self):
            seen.update(cost=self.interp.statement_cost_s, pc=self.interp.get("IRB120Socket:PC_ADDRESS"))
            url = super().start()
            self.interp.request_stop()
            return url

    monkeypatch.setattr(module, "ControllerEmulator", Probe)
    assert main(["emulator", "--statement-cost-us", "25", "--pc-address", "10.0.0.7"]) == 0
    assert seen == dict(cost=pytest.approx(25e-6), pc="10.0.0.7")
    assert main(["emulator"]) == 0  # the defaults: the estimate, and the local client's address
    assert seen == dict(cost=pytest.approx(module.STATEMENT_COST_US * 1e-6), pc="127.0.0.1")
    capsys.readouterr()
    assert main(["emulator", "--statement-cost-us", "-1"]) == 2
    assert "--statement-cost-us -1.0: a time >= 0 us per statement" in capsys.readouterr().err
    assert main(["emulator", "--pc-address", "robot-pc"]) == 2
    assert "--pc-address 'robot-pc': an IPv4 address" in capsys.readouterr().err
    assert main(["emulator", "--listen", "serial://pty", "--pc-address", "10.0.0.7"]) == 2
    assert "only the TCP build serves a PC address" in capsys.readouterr().err
