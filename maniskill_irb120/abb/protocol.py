"""The wire protocol between the PC and our RAPID server on the IRC5 (specification: ``docs/protocol.md``).

Binary frames sized for the slowest common IRC5 serial link: at 9600 baud 8N1 (960 bytes/s) the largest
command (15 bytes) and the state reply (32 bytes) each fit a 50 ms control period with room to spare.
This module only encodes and decodes; transports and the safety envelope live beside it.
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from enum import IntEnum

SYNC = 0xA5
HEADER = 4  # sync, length, type, sequence
OVERHEAD = HEADER + 2  # + CRC-16
MAX_PAYLOAD = 32  # a longer length byte is noise: the parser resynchronises
# a frame still incomplete when nothing more has come for this long will not complete (a truncated frame, or a
# corrupted length byte claiming more than came): the parser drops its sync and scans the bytes after it again. A
# reply (32 bytes) takes 33 ms at 9600 baud and comes in one write.
FRAME_GAP_S = 0.1

# fixed-point units (one definition for both sides; the RAPID module has the same constants)
STEP_UNIT_M = 1e-5  # tool-step translation: 0.01 mm
STEP_UNIT_RAD = math.radians(0.001)  # tool-step rotation: 0.001 degree
JOINT_UNIT_RAD = math.radians(0.02)  # joint angles: 1/50 degree (int16 covers ±655°, axis 6 needs ±400°)
POS_UNIT_M = 5e-5  # TCP position in the reply: 0.05 mm (int16 covers ±1.6 m)
QUAT_UNIT = 1 / (32767 * math.sqrt(2))  # reply quaternion: the three smallest of w, x, y, z ("smallest three")


PROTOCOL_VERSION = 1  # what HELLO carries; the RAPID module's PROTOCOL_VERSION

# The reset's speed (the RAPID module's vReset: TCP mm/s, reorientation deg/s): the PC waits as long as it takes
RESET_TCP_MM_S = 100.0
RESET_ORI_DEG_S = 45.0


class MsgType(IntEnum):
    STATE = 0x01  # read the state; also the heartbeat
    TOOL_STEP = 0x02  # tool-frame step (pd_ee_delta_tool semantics) + gripper
    JOINTS = 0x03  # absolute joint target + gripper
    GRIPPER = 0x04  # gripper only
    STOP = 0x05  # stop and hold (StopMove, ClearPath)
    HELLO = 0x06  # a new session: the controller forgets the previous peer's sequence numbers
    RESET = 0x07  # one slow joint move to a start pose, validated along its path; answered on arrival
    REPLY = 0x80  # OR-ed with the command's type: the reply carries the state


class Status(IntEnum):
    IDLE = 0
    MOVING = 1
    HELD = 2  # stopped by STOP, the watchdog or a restart; an accepted motion command moves it again (docs/protocol.md)
    FAULT = 3  # motors off, emergency stop: nothing moves until the operator clears it


class ErrorCode(IntEnum):
    OK = 0
    STEP_LIMIT = 1
    WORKSPACE = 2
    UNREACHABLE = 3
    JOINT_LIMIT = 4
    BAD_LENGTH = 5
    UNKNOWN_TYPE = 6
    WATCHDOG = 7
    MOTORS_OFF = 8
    ESTOP = 9
    JOINT_SPEED = 10
    OPERATING_MODE = 11
    RESTARTED = 12
    VERSION = 13
    BAD_VALUE = 14


ERROR_MEANINGS = {
    ErrorCode.OK: "accepted",
    ErrorCode.STEP_LIMIT: "refused: the step exceeds the per-step limit (1 cm per axis, 10 degrees)",
    ErrorCode.WORKSPACE: "refused: the target TCP is outside the workspace box",
    ErrorCode.UNREACHABLE: "refused: CalcJointT found no joint solution (outside reach)",
    ErrorCode.JOINT_LIMIT: "refused: the target is outside a joint's limits",
    ErrorCode.BAD_LENGTH: "refused: the payload length does not match the message type",
    ErrorCode.UNKNOWN_TYPE: "refused: unknown message type",
    ErrorCode.WATCHDOG: "refused: the robot was moving and no frame came within the heartbeat timeout, so the "
    "controller stopped and held it; send the command again",
    ErrorCode.MOTORS_OFF: "refused: motors are off (controller error)",
    ErrorCode.ESTOP: "refused: emergency stop is active",
    ErrorCode.JOINT_SPEED: "refused: a joint would move more than its per-step limit",
    ErrorCode.OPERATING_MODE: "refused: the controller is not in manual reduced speed (set the key switch to manual, "
    "or ALLOW_AUTO after a risk assessment)",
    ErrorCode.RESTARTED: "refused: the program was stopped (emergency stop, enabling device, Stop button) and started "
    "again; the controller holds the robot and refuses motion until a new session: call ABBRobot.hello()",
    ErrorCode.VERSION: "refused: the controller's RAPID server speaks another protocol version (load the RAPID files "
    "of this package version)",
    ErrorCode.BAD_VALUE: "refused: a field holds a value the protocol does not define (a gripper byte other than 0 "
    "close, 1 open, 2 keep; GRIPPER: 0 or 1)",
}


class ProtocolError(ValueError):
    """A frame or payload that cannot be encoded or decoded; the message says which and why."""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF): a few shifts per byte, simple to write in RAPID."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


@dataclass(frozen=True)
class Frame:
    type: int
    seq: int
    payload: bytes = b""

    def encode(self) -> bytes:
        if not 0 <= self.type <= 255 or not 0 <= self.seq <= 255:
            raise ProtocolError(f"type {self.type} and seq {self.seq} must be bytes (0..255)")
        if len(self.payload) > MAX_PAYLOAD:
            raise ProtocolError(f"payload of {len(self.payload)} bytes exceeds {MAX_PAYLOAD}")
        body = bytes([len(self.payload), self.type, self.seq]) + self.payload
        return bytes([SYNC]) + body + struct.pack("<H", crc16(body))


class FrameParser:
    """Incremental, resynchronising decoder: ``feed(bytes)`` returns the complete frames; bytes before a sync are
    skipped, and a sync whose length byte is over MAX_PAYLOAD or whose CRC fails is dropped alone: the scan resumes
    at the byte after it with every byte after it kept, so a corrupted frame never swallows the valid one behind it
    (counted in ``dropped_bytes`` / ``bad_frames``). A frame that stays incomplete (truncated, or a corrupted length
    claiming more than came) is dropped the same way by :meth:`expire` once the line has been quiet for
    ``gap_s``; the reader calls it when a read returns nothing."""

    def __init__(self, gap_s: float = FRAME_GAP_S) -> None:
        if not (math.isfinite(gap_s) and gap_s > 0):
            raise ProtocolError(f"gap_s={gap_s!r}: a positive time in seconds")
        self.gap_s = gap_s
        self.buf = bytearray()
        self.dropped_bytes = 0
        self.bad_frames = 0
        self.last_byte_at = -math.inf  # time.monotonic() of the last byte fed

    def expire(self, now: float | None = None) -> list[Frame]:
        """The frames found once an incomplete frame is given up: when nothing has come for ``gap_s`` (by ``now``,
        time.monotonic()), the pending frame's sync is dropped and the bytes after it scanned again, until none is
        pending. Nothing changes while bytes may still be on their way."""
        now = time.monotonic() if now is None else now
        frames: list[Frame] = []
        if now - self.last_byte_at < self.gap_s:
            return frames
        while self.buf:  # feed leaves the buffer empty or starting at the sync of an incomplete frame
            self.bad_frames += 1
            self.dropped_bytes += 1
            del self.buf[:1]
            frames += self._scan()
        return frames

    def feed(self, data: bytes) -> list[Frame]:
        if data:
            self.buf += data
            self.last_byte_at = time.monotonic()
        return self._scan()

    def _scan(self) -> list[Frame]:
        frames = []
        while True:
            start = self.buf.find(SYNC)
            if start < 0:
                self.dropped_bytes += len(self.buf)
                self.buf.clear()
                return frames
            if start:
                self.dropped_bytes += start
                del self.buf[:start]
            if len(self.buf) < 2:
                return frames
            n = self.buf[1]
            if n > MAX_PAYLOAD:  # not a frame start: skip this sync byte and look again
                self.dropped_bytes += 1
                del self.buf[:1]
                continue
            size = OVERHEAD + n
            if len(self.buf) < size:
                return frames
            body, (crc,) = bytes(self.buf[1 : size - 2]), struct.unpack("<H", self.buf[size - 2 : size])
            if crc16(body) != crc:
                self.bad_frames += 1
                self.dropped_bytes += 1
                del self.buf[:1]  # the sync may have been a data byte: resynchronise from the next one
                continue
            frames.append(Frame(body[1], body[2], body[3:]))
            del self.buf[:size]


def _fixed(value: float, unit: float, what: str, lo: int = -32768, hi: int = 32767) -> int:
    if not math.isfinite(value):
        raise ProtocolError(f"{what}={value} is not finite")
    n = round(value / unit)
    if not lo <= n <= hi:
        raise ProtocolError(f"{what}={value} is outside what the protocol carries ({lo * unit}..{hi * unit})")
    return n


def _gripper_byte(gripper_open: bool | None) -> int:
    return 2 if gripper_open is None else int(bool(gripper_open))  # 2: keep the gripper as it is


def _gripper_from(b: int) -> bool | None:
    if b not in (0, 1, 2):
        raise ProtocolError(f"gripper byte {b} is not 0 (close), 1 (open) or 2 (keep)")
    return None if b == 2 else bool(b)


@dataclass(frozen=True)
class ToolStep:
    """Translate by ``d`` (m, tool frame), then rotate by ``rot`` (rad) about the approach axis (tool x)."""

    dx: float
    dy: float
    dz: float
    rot: float
    gripper_open: bool | None = None
    TYPE = MsgType.TOOL_STEP

    def payload(self) -> bytes:
        d = [_fixed(v, STEP_UNIT_M, n) for v, n in ((self.dx, "dx"), (self.dy, "dy"), (self.dz, "dz"))]
        return struct.pack("<4hB", *d, _fixed(self.rot, STEP_UNIT_RAD, "rot"), _gripper_byte(self.gripper_open))

    @classmethod
    def parse(cls, p: bytes) -> ToolStep:
        dx, dy, dz, rot, g = _unpack("<4hB", p, cls.TYPE)
        return cls(dx * STEP_UNIT_M, dy * STEP_UNIT_M, dz * STEP_UNIT_M, rot * STEP_UNIT_RAD, _gripper_from(g))


@dataclass(frozen=True)
class Joints:
    """Absolute joint target (6 angles, rad)."""

    q: tuple[float, ...]
    gripper_open: bool | None = None
    TYPE = MsgType.JOINTS

    def payload(self) -> bytes:
        if len(self.q) != 6:
            raise ProtocolError(f"a joint target has 6 angles, got {len(self.q)}")
        q = [_fixed(v, JOINT_UNIT_RAD, f"q{i + 1}") for i, v in enumerate(self.q)]
        return struct.pack("<6hB", *q, _gripper_byte(self.gripper_open))

    @classmethod
    def parse(cls, p: bytes) -> Joints:
        *q, g = _unpack("<6hB", p, cls.TYPE)
        return cls(tuple(v * JOINT_UNIT_RAD for v in q), _gripper_from(g))


@dataclass(frozen=True)
class Gripper:
    open: bool
    TYPE = MsgType.GRIPPER

    def payload(self) -> bytes:
        return bytes([int(bool(self.open))])

    @classmethod
    def parse(cls, p: bytes) -> Gripper:
        (g,) = _unpack("<B", p, cls.TYPE)
        if g not in (0, 1):
            raise ProtocolError(f"gripper byte {g} is not 0 (close) or 1 (open)")
        return cls(bool(g))


@dataclass(frozen=True)
class GetState:
    TYPE = MsgType.STATE

    def payload(self) -> bytes:
        return b""

    @classmethod
    def parse(cls, p: bytes) -> GetState:
        _unpack("<", p, cls.TYPE)
        return cls()


@dataclass(frozen=True)
class Stop(GetState):
    TYPE = MsgType.STOP

    @classmethod
    def parse(cls, p: bytes) -> Stop:
        _unpack("<", p, cls.TYPE)
        return cls()


@dataclass(frozen=True)
class Hello:
    """Opens a session: the controller drops its duplicate cache, so a sequence number this PC used before (or
    another PC used) is never answered with an old reply."""

    version: int = PROTOCOL_VERSION
    TYPE = MsgType.HELLO

    def payload(self) -> bytes:
        if not 0 <= self.version <= 255:
            raise ProtocolError(f"protocol version {self.version} is not a byte")
        return bytes([self.version])

    @classmethod
    def parse(cls, p: bytes) -> Hello:
        (v,) = _unpack("<B", p, cls.TYPE)
        return cls(v)


@dataclass(frozen=True)
class Reset(Joints):
    """One slow joint move to ``q`` (the episode's start pose), validated by the controller along its path."""

    TYPE = MsgType.RESET


COMMANDS = {c.TYPE: c for c in (GetState, ToolStep, Joints, Gripper, Stop, Hello, Reset)}
# head byte: status (bits 0-1) | index of the quaternion's largest component (bits 2-3) | gripper open (bit 7);
# error; joints; target TCP position; the quaternion's other three components, with the largest made positive
STATE_FORMAT = "<BB6h3h3h"


@dataclass(frozen=True)
class RobotState:
    """The controller's reply to every command: its state when it answered, and the command's outcome.

    ``target_*`` is the TCP pose the controller is taking the robot to (its last queued motion; where the TCP
    stands once the robot is still): the pose a next step may start from, which the PC's envelope needs. The
    measured TCP is not on the wire (it is the joints' forward kinematics): ``ABBRobot`` fills ``tcp_*`` in."""

    joints: tuple[float, ...]  # rad, measured
    target_pos: tuple[float, float, float]  # m, robot base frame
    target_quat: tuple[float, float, float, float]  # wxyz (decoded with its largest component positive)
    gripper_open: bool
    status: Status
    error: ErrorCode
    tcp_pos: tuple[float, float, float] | None = None  # m, measured: FK of ``joints`` (client side)
    tcp_quat: tuple[float, float, float, float] | None = None

    def payload(self) -> bytes:
        # "smallest three": dropping the largest component (>= 1/2, recovered well conditioned) keeps the
        # other three in ±1/√2, so int16 carries them to 2e-5 whatever the orientation
        quat = list(self.target_quat)
        big = max(range(4), key=lambda i: abs(quat[i]))
        sign = -1.0 if quat[big] < 0 else 1.0
        rest = [sign * v for i, v in enumerate(quat) if i != big]
        head = int(self.status) | big << 2 | (0x80 if self.gripper_open else 0)
        q = [_fixed(v, JOINT_UNIT_RAD, f"joint {i + 1}") for i, v in enumerate(self.joints)]
        p = [_fixed(v, POS_UNIT_M, n) for v, n in zip(self.target_pos, "xyz")]
        r = [_fixed(v, QUAT_UNIT, "quaternion component") for v in rest]
        return struct.pack(STATE_FORMAT, head, int(self.error), *q, *p, *r)

    @classmethod
    def parse(cls, p: bytes) -> RobotState:
        head, err, *rest = _unpack(STATE_FORMAT, p, MsgType.REPLY)
        q, pos, small = rest[:6], rest[6:9], [v * QUAT_UNIT for v in rest[9:]]
        big = head >> 2 & 3
        small.insert(big, math.sqrt(max(0.0, 1.0 - sum(v * v for v in small))))
        try:
            status, error = Status(head & 3), ErrorCode(err)
        except ValueError as e:
            raise ProtocolError(f"state reply: {e}") from None
        joints = tuple(v * JOINT_UNIT_RAD for v in q)
        return cls(joints, tuple(v * POS_UNIT_M for v in pos), tuple(small), bool(head & 0x80), status, error)

    @property
    def meaning(self) -> str:
        return ERROR_MEANINGS[self.error]


def _unpack(fmt: str, payload: bytes, msg_type: int) -> tuple:
    size = struct.calcsize(fmt)
    if len(payload) != size:
        name = MsgType(msg_type).name if msg_type in MsgType._value2member_map_ else hex(msg_type)
        raise ProtocolError(f"{name} payload has {len(payload)} bytes, expected {size}")
    return struct.unpack(fmt, payload)


def command_frame(msg, seq: int) -> Frame:
    return Frame(int(msg.TYPE), seq, msg.payload())


def reply_frame(command_type: int, seq: int, state: RobotState) -> Frame:
    return Frame(MsgType.REPLY | command_type, seq, state.payload())


def decode_command(frame: Frame):
    if frame.type not in COMMANDS:
        raise ProtocolError(f"unknown command type 0x{frame.type:02x}")
    return COMMANDS[frame.type].parse(frame.payload)


def decode_reply(frame: Frame) -> RobotState:
    if not frame.type & MsgType.REPLY or frame.type & 0x7F not in COMMANDS:
        raise ProtocolError(f"0x{frame.type:02x} is not a reply type")
    return RobotState.parse(frame.payload)
