"""The client's transport and retry rules over a real pty pair (serial) and TCP loopback, against a scripted
peer that speaks the protocol and can lose, corrupt or delay replies. What the controller does with a command
is tested against the emulator running our RAPID module, not here."""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest

pytest.importorskip("serial")

from maniskill_irb120.abb.client import (  # noqa: E402
    ABBRobot,
    ControllerRefused,
    ControllerStopped,
    RobotError,
    RobotTimeout,
    open_port,
)
from maniskill_irb120.abb.envelope import Envelope, EnvelopeError  # noqa: E402
from maniskill_irb120.abb.protocol import (  # noqa: E402
    ErrorCode,
    FrameParser,
    RobotState,
    Status,
    ToolStep,
    decode_command,
    reply_frame,
)
from maniskill_irb120.robot.irb120 import IRB120Metalwork  # noqa: E402
from maniskill_irb120.robot.kinematics import matrix_to_quat  # noqa: E402

REST = tuple(float(v) for v in IRB120Metalwork.keyframes["rest"].qpos[:6])
_REST_TCP = Envelope().tcp_pose(REST)  # the peer reports a consistent pose: the client steps from it
REST_POS, REST_QUAT = tuple(_REST_TCP[:3, 3]), tuple(matrix_to_quat(_REST_TCP[:3, :3]))


class ScriptedPeer:
    """Answers each frame with a state reply; executes a sequence number once and answers repeats from its
    cache, as the protocol requires. ``faults`` maps the n-th received frame (1-based) to drop|corrupt|delay."""

    def __init__(self, read, write, faults=None, error=ErrorCode.OK):
        self.read, self.write, self.faults, self.error = read, write, dict(faults or {}), error
        self.received, self.executed, self.last = 0, [], None
        self.commands = []
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.alive = True
        self.thread.start()

    def run(self):
        parser = FrameParser()
        while self.alive:
            data = self.read()
            if not data:
                continue
            for frame in parser.feed(data):
                self.received += 1
                if self.last is None or frame.seq != self.last[0]:
                    self.executed.append(frame.seq)
                    self.commands.append(decode_command(frame))
                    state = RobotState(REST, REST_POS, REST_QUAT, True, Status.IDLE, self.error)
                    self.last = (frame.seq, reply_frame(frame.type, frame.seq, state).encode())
                reply = self.last[1]
                fault = self.faults.get(self.received)
                if fault == "drop":
                    continue
                if fault == "corrupt":
                    reply = reply[:10] + bytes([reply[10] ^ 0xFF]) + reply[11:]
                if fault == "delay":
                    time.sleep(0.4)
                self.write(reply)


@pytest.fixture
def pty_pair():
    """(peer factory, client URL) over a fresh pty pair; the peer's thread ends before the pty is closed."""
    import select

    master, slave = os.openpty()
    peers = []

    def start(**kw) -> ScriptedPeer:
        def read():
            r, _, _ = select.select([master], [], [], 0.05)
            return os.read(master, 256) if r else b""

        peers.append(ScriptedPeer(read, lambda b: os.write(master, b), **kw))
        return peers[-1]

    yield start, f"serial://{os.ttyname(slave)}?baudrate=115200"
    for p in peers:
        p.alive = False
        p.thread.join(1)
    os.close(master)
    os.close(slave)


def test_serial_state_and_tool_step(pty_pair):
    start, url = pty_pair
    peer = start()
    with ABBRobot.connect(url) as robot:
        s = robot.state()
        assert s.status == Status.IDLE and s.gripper_open and np.allclose(s.joints, REST, atol=1e-3)
        robot.move_tool([0.5, -1.5, 0.0, 0.2, -1.0])  # clipped and scaled as the sim does
    step = peer.commands[2]  # after the state read by connect() and by state()
    assert isinstance(step, ToolStep) and step.gripper_open is False
    np.testing.assert_allclose([step.dx, step.dy, step.dz], [0.005, -0.01, 0.0], atol=1e-5)
    assert peer.executed == [1, 2, 3, 4]  # connect, state, step, the stop on exit


@pytest.mark.parametrize("fault", ["drop", "corrupt", "delay"])
def test_a_lost_or_bad_reply_is_retried_without_repeating_the_command(pty_pair, fault):
    start, url = pty_pair
    peer = start(faults={2: fault})
    robot = ABBRobot.connect(url)
    robot.move_tool([0.1, 0, 0, 0, 1])
    deadline = time.monotonic() + 1.0  # "delay": the late original reply may win; the resent frame still arrives
    while peer.received < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert peer.received == 3 and peer.executed == [1, 2]  # the step's frame came twice, ran once
    robot.port.close()


def test_timeout_names_the_command_and_the_connection_stays_usable(pty_pair):
    start, url = pty_pair
    peer = start(faults={2: "drop", 3: "drop", 4: "drop"})
    robot = ABBRobot.connect(url, timeout=0.1, retries=2)
    with pytest.raises(RobotTimeout, match=r"ToolStep \(seq 2\).*3 attempts"):
        robot.move_tool([0.1, 0, 0, 0, 1])
    assert robot.state().status == Status.IDLE  # next command, next number
    assert peer.executed == [1, 2, 3]
    robot.port.close()


def test_silence_after_a_motion_command_says_check_the_pendant(pty_pair):
    """A motion command met by silence reads as a stopped controller (emergency stop, enabling device, program
    stopped: the issue's client finding), a subclass of RobotTimeout; a silent STATE read keeps the plain timeout."""
    start, url = pty_pair
    start(faults={k: "drop" for k in range(2, 8)})
    robot = ABBRobot.connect(url, timeout=0.05, retries=2)
    with pytest.raises(ControllerStopped, match=r"check the pendant .*enabling device.*ToolStep \(seq 2\).*3 attempts"):
        robot.move_tool([0.1, 0, 0, 0, 1])
    with pytest.raises(RobotTimeout) as e:
        robot.state()
    assert not isinstance(e.value, ControllerStopped) and "pendant" not in str(e.value)
    robot.port.close()


def test_refusals_and_bad_input(pty_pair):
    start, url = pty_pair
    peer = start(error=ErrorCode.WORKSPACE)
    robot = ABBRobot(open_port(url, 0.25))
    with pytest.raises(ControllerRefused, match="outside the workspace box") as e:
        robot.state()
    assert e.value.state.error == ErrorCode.WORKSPACE
    peer.error = ErrorCode.OK
    with pytest.raises(ValueError, match="5 finite numbers"):
        robot.move_tool([0.0, float("nan"), 0, 0, 1])
    sent = peer.received
    with pytest.raises(EnvelopeError, match="joint_speed"):
        robot.move_joints(np.asarray(REST) + [0.5, 0, 0, 0, 0, 0])
    assert peer.received == sent  # refused before anything went on the wire
    robot.close()
    with pytest.raises(RobotError, match="closed"):
        robot.state()
    with pytest.raises(ValueError, match="unknown transport"):
        open_port("udp://1.2.3.4:5", 0.1)


def test_tcp_loopback():
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    conns = []

    def accept():
        conn, _ = server.accept()
        conn.settimeout(0.05)
        conns.append(conn)

        def read():
            try:
                return conn.recv(256)
            except (TimeoutError, OSError):
                return b""

        conns.append(ScriptedPeer(read, conn.sendall))

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    with ABBRobot.connect(f"tcp://127.0.0.1:{port}") as robot:
        robot.move_tool([0, 0, 0, 1.0, 1.0])
    t.join(1)
    assert conns[1].executed == [1, 2, 3]
    conns[1].alive = False
    conns[0].close()
    server.close()
