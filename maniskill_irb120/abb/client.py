"""``ABBRobot``: the env's action space on an ABB IRC5 running our RAPID server (protocol: docs/protocol.md).

Transports by URL through pyserial's ``serial_for_url`` (no serial code of ours): ``serial:///dev/ttyUSB0?
baudrate=9600`` for the licence-free serial channel, ``tcp://host:port`` for controllers with 616-1 PC Interface.
Every command is checked against the safety envelope before it is sent (the controller checks again). A command
that gets no valid reply in time is resent byte for byte, same sequence number: the controller answers a
repeated number without executing it again, so a retry never repeats a motion.

    with ABBRobot.connect("tcp://192.168.125.1:5000") as robot:
        state = robot.state()
        state = robot.move_tool([0.0, 0.5, 0.0, 1.0, 1.0])   # the env's normalised 5-vector
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import replace
from urllib.parse import parse_qs, urlparse

import numpy as np

from maniskill_irb120.abb.envelope import Envelope
from maniskill_irb120.abb.protocol import (
    ERROR_MEANINGS,
    FRAME_GAP_S,
    RESET_ORI_DEG_S,
    RESET_TCP_MM_S,
    ErrorCode,
    FrameParser,
    GetState,
    Gripper,
    Hello,
    Joints,
    MsgType,
    ProtocolError,
    Reset,
    RobotState,
    Status,
    Stop,
    ToolStep,
    command_frame,
    decode_reply,
)
from maniskill_irb120.action import gripper_opens, scale_tool_action
from maniskill_irb120.robot.kinematics import matrix_to_quat, pose_mm


def _target(state: RobotState) -> np.ndarray:
    """The pose (4x4, m) the controller is taking the TCP to, as its reply says."""
    return pose_mm(np.asarray(state.target_pos) * 1000, state.target_quat)


log = logging.getLogger(__name__)

LOOKAHEAD_TARGETS = 3
# How long connect resends its HELLO: the TCP server serves one client at a time and turns to a new one once the
# current one closes, or has been silent for 1 s while this one waits (IRB120Server.mod SILENCE_S; about 1.5 s after
# this one connects, docs/protocol.md), and drops what this one sent before it turned to it. With a margin.
CONNECT_WAIT_S = 2.5
RESET_CHECK_STEP = np.radians(np.full(6, 2.0))  # the reset's joint path is checked every 2 degrees


class RobotError(RuntimeError):
    """Base of the client's errors: each says what happened."""


class RobotTimeout(RobotError):
    pass


class ControllerStopped(RobotTimeout):
    """A motion command (tool step, joints, gripper) got no valid reply: the controller most likely stopped
    (emergency stop, motors off, enabling device released, program stopped), not just a slow line."""


STOPPED_HINT = (
    "the controller stopped answering after a command: check the pendant "
    "(emergency stop, motors off, enabling device, program stopped)"
)
MOTION_TYPES = (MsgType.TOOL_STEP, MsgType.JOINTS, MsgType.GRIPPER, MsgType.RESET)


class RobotDisconnected(RobotError):
    pass


class ControllerRefused(RobotError):
    def __init__(self, state: RobotState):
        super().__init__(f"controller refused the command: {ERROR_MEANINGS[state.error]} (code {int(state.error)})")
        self.state = state


def open_port(url: str, timeout: float):
    """A pyserial port for ``serial://DEVICE?baudrate=N`` or ``tcp://HOST:PORT`` (pyserial's socket handler)."""
    import serial  # the ``real`` extra

    u = urlparse(url)
    if u.scheme == "tcp":
        if not u.hostname or not u.port:
            raise ValueError(f"{url!r}: a TCP URL is tcp://HOST:PORT")
        return serial.serial_for_url(f"socket://{u.hostname}:{u.port}", timeout=timeout)
    if u.scheme == "serial":
        query = parse_qs(u.query)
        unknown = set(query) - {"baudrate"}
        if not u.path or unknown:
            raise ValueError(f"{url!r}: a serial URL is serial:///dev/DEVICE[?baudrate=N] (unknown: {sorted(unknown)})")
        baud = int(query.get("baudrate", ["9600"])[0])
        return serial.serial_for_url(u.path, baudrate=baud, bytesize=8, parity="N", stopbits=1, timeout=timeout)
    raise ValueError(f"{url!r}: unknown transport {u.scheme!r}; use serial:///dev/DEVICE?baudrate=N or tcp://HOST:PORT")


class ABBRobot:
    """One connection to the RAPID server. Use :meth:`connect` (a context manager that stops the robot on exit)."""

    def __init__(self, port, timeout: float = 0.25, retries: int = 2, envelope: Envelope | None = None):
        self.port, self.timeout, self.retries = port, timeout, retries
        self.envelope = envelope or Envelope()
        self.check_envelope = True  # tests of the controller side alone turn this off
        self.parser = FrameParser()
        self.seq = 0
        self.last_state: RobotState | None = None
        # the motion targets the last replies reported (4x4): the robot may still be on its way through them
        # when the next frame arrives (the module's MoveL returns with one segment of look-ahead, so up to two
        # are queued; one more is kept for a real IRC5's deeper path planning)
        self.pending: deque[np.ndarray] = deque(maxlen=LOOKAHEAD_TARGETS)

    @classmethod
    def connect(
        cls,
        url: str,
        timeout: float = 0.25,
        retries: int = 2,
        envelope: Envelope | None = None,
        wait: float = CONNECT_WAIT_S,
    ) -> ABBRobot:
        """Open the port and a session. The HELLO is resent every ``timeout`` for up to ``wait`` seconds
        (:data:`CONNECT_WAIT_S`): a controller serving another client turns to this one only once that client
        closes or falls silent, and drops what this one sent before. Raises :class:`RobotTimeout` saying so if
        nothing answers."""
        if not (math.isfinite(wait) and wait >= 0):
            raise ValueError(f"wait={wait!r}: how long to wait for the controller to answer, in seconds (>= 0)")
        robot = cls(open_port(url, timeout), timeout, retries, envelope)
        try:
            robot.hello(wait)  # fail now, not at the first motion, if nothing answers
        except RobotError:
            robot.port.close()
            raise
        return robot

    def hello(self, wait: float = 0.0) -> RobotState:
        """Open a session: the controller forgets earlier sequence numbers (ours or another PC's), so none of
        them is answered with an old reply, and lifts its restart hold. ``connect`` does this; a client that
        reopens its port does it again. ``wait``: keep resending it (every ``timeout``) for that long, as connect
        does while the controller is serving another client."""
        attempts = max(1 + self.retries, math.ceil(wait / self.timeout))
        return self._request(Hello(), attempts=attempts)

    def __enter__(self) -> ABBRobot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ commands
    def state(self) -> RobotState:
        return self._request(GetState())

    def move_tool(self, action) -> RobotState:
        """The env's ``pd_ee_delta_tool`` action (5 numbers in [-1, 1], clipped and scaled as the sim does)."""
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (5,) or not np.all(np.isfinite(a)):
            raise ValueError(f"a tool action is 5 finite numbers, got {action!r}")
        step = scale_tool_action(a[:4])
        if self.check_envelope:
            # the controller applies the step to the pose it measures when the frame arrives: somewhere on the
            # path from the last reply's joints through the targets still queued. The step taken from each
            # corner of that path must stay inside the envelope (between corners the margin covers the bow of
            # the slerped orientation, < 0.1 mm for a full step)
            q_now = self._joints_now()
            self.envelope.check_tool_step(q_now, step[:3], float(step[3]))
            for pose in self.pending:
                q = self.envelope.solve(pose, q_now)
                self.envelope.check_tool_step(q, step[:3], float(step[3]), tcp_now=pose)
        return self._request(ToolStep(*map(float, step), bool(gripper_opens(a[4]))))

    def move_joints(self, q, gripper_open: bool | None = None) -> RobotState:
        q = np.asarray(q, dtype=np.float64)
        if self.check_envelope:
            self.envelope.check_joints(self._joints_now(), q)
        return self._request(Joints(tuple(map(float, q)), gripper_open))

    def reset(self, q, gripper_open: bool | None = None) -> RobotState:
        """One slow joint move to ``q`` (rad; an episode's start pose): the envelope checks the whole joint path
        here, the controller checks it again and moves at its reset speed (protocol.RESET_TCP_MM_S), ending at a
        stop point. Waits for the reply as long as the move takes."""
        q = np.asarray(q, dtype=np.float64)
        q_now = self._joints_now()
        if self.check_envelope:
            self.envelope.plan_move(q_now, q, RESET_CHECK_STEP)
        seconds = self.envelope.move_seconds(q_now, q, RESET_TCP_MM_S / 1000, np.radians(RESET_ORI_DEG_S))
        self.pending.clear()
        return self._request(Reset(tuple(map(float, q)), gripper_open), timeout=self.timeout + 1.5 * seconds + 0.5)

    def set_gripper(self, open_: bool) -> RobotState:
        return self._request(Gripper(bool(open_)))

    def stop(self) -> RobotState:
        self.pending.clear()  # the controller clears its path: the robot holds where the reply says
        return self._request(Stop())

    def close(self) -> None:
        """Stop the robot (best effort), then close the port."""
        if self.port is None:
            return
        try:
            self.stop()
        except RobotError:
            pass
        finally:
            self.port.close()
            self.port = None

    # ------------------------------------------------------------------ internals
    def _joints_now(self) -> np.ndarray:
        return np.asarray((self.last_state or self.state()).joints)

    def _request(self, msg, timeout: float | None = None, attempts: int | None = None) -> RobotState:
        if self.port is None:
            raise RobotError("the robot connection is closed")
        self.seq = self.seq % 255 + 1  # 1..255: a fresh number for every new command
        raw = command_frame(msg, self.seq).encode()
        want = MsgType.REPLY | msg.TYPE
        bad_before = self.parser.bad_frames
        attempts = 1 + self.retries if attempts is None else attempts
        for attempt in range(attempts):
            if attempt == 1 and msg.TYPE == MsgType.HELLO and attempts > 1 + self.retries:
                log.info(
                    "no reply to HELLO yet: waiting up to %.1f s for the controller to turn to this connection (it "
                    "serves one client at a time, and replaces one only once it closes or is silent for 1 s)",
                    attempts * self.timeout,
                )
            try:
                self.port.write(raw)  # a retry is the same bytes: the controller answers it without executing it
                state = self._await_reply(want, self.seq, self.timeout if timeout is None else timeout)
            except (OSError, ValueError) as e:  # pyserial's SerialException is an OSError
                raise RobotDisconnected(
                    f"connection to the controller lost during {type(msg).__name__} "
                    f"(seq {self.seq}): {e}; reconnect with ABBRobot.connect"
                ) from None
            if state is not None:
                return self._checked(state)
        corrupt = self.parser.bad_frames - bad_before
        detail = (
            f"no valid reply to {type(msg).__name__} (seq {self.seq}) within "
            f"{self.timeout if timeout is None else timeout:.2f} s, "
            f"{attempts} attempts" + (f"; {corrupt} corrupted frames were discarded" if corrupt else "")
        )
        if msg.TYPE in MOTION_TYPES:  # silence after a command: most likely a stopped controller, not a slow line
            raise ControllerStopped(f"{STOPPED_HINT}: {detail}")
        if msg.TYPE == MsgType.HELLO:
            detail += (
                f" ({attempts * self.timeout:.1f} s): the controller serves one client at a time and turns to a new "
                "one only once the current one closes or has been silent for 1 s; check that no other client keeps "
                "it busy, that its program runs (pendant), the URL and the server's PC_ADDRESS"
            )
        raise RobotTimeout(detail)

    def _await_reply(self, want: int, seq: int, timeout: float) -> RobotState | None:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            self.port.timeout = min(left, FRAME_GAP_S)
            data = self.port.read(max(1, self.port.in_waiting))
            # a quiet line: a frame left incomplete (truncated, a corrupted length) is given up and what came
            # behind it scanned again
            for frame in self.parser.feed(data) if data else self.parser.expire():
                if frame.seq != seq or frame.type != want:
                    continue  # a late reply to an earlier attempt or command
                try:
                    return decode_reply(frame)
                except ProtocolError as e:
                    raise RobotError(f"malformed reply from the controller: {e}") from None
        return None

    def _checked(self, state: RobotState) -> RobotState:
        tcp = self.envelope.tcp_pose(state.joints)
        state = replace(state, tcp_pos=tuple(tcp[:3, 3]), tcp_quat=tuple(matrix_to_quat(tcp[:3, :3])))
        target = _target(state)
        if not self.pending or np.abs(self.pending[-1] - target).max() > 1e-9:
            self.pending.append(target)
        self.last_state = state
        if state.error != ErrorCode.OK:
            raise ControllerRefused(state)
        if state.status == Status.FAULT:
            raise RobotError("controller reports a fault (motors off or emergency stop); clear it on the controller")
        return state
