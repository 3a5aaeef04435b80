"""The wire protocol (docs/protocol.md): the shared test vectors both ways, the incremental parser under
noise, corruption and splitting, range checks, and the 9600-baud budget."""

from __future__ import annotations

import json
import math
import random
import time
from importlib import resources

import pytest

from maniskill_irb120.abb.protocol import (
    OVERHEAD,
    ErrorCode,
    Frame,
    FrameParser,
    GetState,
    Gripper,
    Joints,
    MsgType,
    ProtocolError,
    RobotState,
    Status,
    Stop,
    ToolStep,
    command_frame,
    crc16,
    decode_command,
    decode_reply,
)

VECTORS = json.loads(resources.files("maniskill_irb120.assets").joinpath("rapid", "protocol_vectors.json").read_text())


def message_from(d: dict):
    kind = d["message"]
    if kind == "ToolStep":
        return ToolStep(d["dx"], d["dy"], d["dz"], math.radians(d["rot_deg"]), d["gripper_open"])
    if kind == "Joints":
        return Joints(tuple(math.radians(v) for v in d["q_deg"]), d["gripper_open"])
    if kind == "Gripper":
        return Gripper(d["open"])
    if kind == "RobotState":
        return RobotState(
            tuple(math.radians(v) for v in d["joints_deg"]),
            tuple(d["target_pos"]),
            tuple(d["target_quat"]),
            d["gripper_open"],
            Status[d["status"]],
            ErrorCode[d["error"]],
        )
    return {"GetState": GetState, "Stop": Stop}[kind]()


def test_crc_is_ccitt_false():
    assert crc16(VECTORS["crc_check"]["input_ascii"].encode()) == int(VECTORS["crc_check"]["crc16_ccitt_false"], 16)


@pytest.mark.parametrize("vec", VECTORS["frames"], ids=lambda v: v["name"])
def test_vectors_both_ways(vec):
    raw = bytes.fromhex(vec["hex"])
    msg = message_from(vec["decoded"])
    assert Frame(vec["type"], vec["seq"], msg.payload()).encode() == raw
    (frame,) = FrameParser().feed(raw)
    assert (frame.type, frame.seq) == (vec["type"], vec["seq"])
    decoded = decode_reply(frame) if frame.type & MsgType.REPLY else decode_command(frame)
    assert type(decoded) is type(msg)
    if isinstance(msg, RobotState):
        assert same_state(decoded, msg)
    else:
        assert decoded.payload() == msg.payload()  # equal to the protocol's resolution


def same_state(a: RobotState, b: RobotState) -> bool:
    """Equal to the protocol's resolution; the quaternion as a rotation (q and -q, ties of the largest part)."""
    dot = abs(sum(x * y for x, y in zip(a.target_quat, b.target_quat)))
    return (
        max(abs(x - y) for x, y in zip(a.joints, b.joints)) <= math.radians(0.01) + 1e-9
        and max(abs(x - y) for x, y in zip(a.target_pos, b.target_pos)) <= 2.5e-5 + 1e-9
        and 2 * math.degrees(math.acos(min(1.0, dot))) < 0.01
        and (a.gripper_open, a.status, a.error) == (b.gripper_open, b.status, b.error)
    )


def test_parser_resynchronises_after_noise_corruption_and_splits():
    frames = [command_frame(ToolStep(0.001 * i, 0, 0, 0.01, True), i).encode() for i in range(1, 6)]
    corrupt = bytearray(frames[2])
    corrupt[6] ^= 0x40
    stream = b"\x00\xa5\xff\x13" + frames[0] + frames[1] + bytes(corrupt) + b"\xa5" + frames[3] + frames[4]
    parser, got = FrameParser(), []
    for i in range(0, len(stream), 3):  # arrives in pieces
        got += parser.feed(stream[i : i + 3])
    assert [f.seq for f in got] == [1, 2, 4, 5]  # the corrupted frame is dropped, nothing else lost
    assert parser.bad_frames >= 1 and parser.dropped_bytes >= len(corrupt)


def test_random_corruption_never_yields_a_wrong_frame():
    rng = random.Random(0)
    good = [command_frame(ToolStep(0.0, 0.002, 0.0, 0.0, None), s).encode() for s in range(200)]
    parser, accepted = FrameParser(), 0
    for raw in good:
        b = bytearray(raw)
        if rng.random() < 0.5:
            b[rng.randrange(1, len(b))] ^= 1 << rng.randrange(8)  # one flipped bit
        for f in parser.feed(bytes(b)):
            assert f.encode() in good  # never a frame that was not sent
            accepted += 1
    assert 60 < accepted < 200


@pytest.mark.parametrize(
    "bad, match",
    [
        (lambda: ToolStep(0.5, 0, 0, 0).payload(), "dx=0.5"),
        (lambda: ToolStep(0, float("nan"), 0, 0).payload(), "not finite"),
        (lambda: Joints((0.0,) * 5).payload(), "6 angles"),
        (lambda: Joints((0, 0, 0, 0, 0, math.radians(700))).payload(), "q6"),
        (lambda: ToolStep.parse(b"\x00" * 8), "TOOL_STEP payload has 8 bytes, expected 9"),
        (lambda: Gripper.parse(b"\x07"), "gripper byte 7"),
        (lambda: decode_command(Frame(0x33, 1)), "unknown command type 0x33"),
        (lambda: decode_reply(Frame(0x02, 1, b"")), "not a reply"),
        (lambda: Frame(1, 300).encode(), "seq 300"),
    ],
)
def test_bad_values_raise_clear_errors(bad, match):
    with pytest.raises(ProtocolError, match=match):
        bad()


def test_state_round_trip_within_resolution():
    rng = random.Random(1)
    for _ in range(200):
        q = [rng.gauss(0, 1) for _ in range(4)]
        n = math.sqrt(sum(v * v for v in q))
        quat = tuple(v / n for v in q)
        joints = tuple(rng.uniform(-2.8, 2.8) for _ in range(5)) + (rng.uniform(-6.9, 6.9),)
        s = RobotState(
            joints,
            (rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(0, 0.87)),
            quat,
            rng.random() < 0.5,
            Status.MOVING,
            ErrorCode.OK,
        )
        assert same_state(RobotState.parse(s.payload()), s)


def test_frames_fit_20_hz_at_9600_baud():
    """A command and its reply each fit the ~48 bytes one 50 ms period carries at 9600 baud 8N1; even a
    tool step and its reply back to back (half duplex, worst case) take under 50 ms on the wire."""
    reply = OVERHEAD + len(RobotState((0.0,) * 6, (0, 0, 0), (1, 0, 0, 0), False, Status.IDLE, ErrorCode.OK).payload())
    sizes = {
        m: len(command_frame(m, 1).encode())
        for m in (GetState(), ToolStep(0, 0, 0, 0), Joints((0.0,) * 6), Gripper(True), Stop())
    }
    assert max(sizes.values()) <= 48 and reply <= 48
    wire_s = lambda n: n * 10 / 9600  # noqa: E731  (start + 8 data + stop bits)
    assert wire_s(sizes[ToolStep(0, 0, 0, 0)] + reply) < 0.050


# each class of corruption the original report found swallowing the valid frame behind it
STEP_RAW = command_frame(ToolStep(0.006, 0.0, 0.0, 0.0), 9).encode()
CORRUPTIONS = {
    "truncated frame": STEP_RAW[:8],
    "length 32 header": bytes([0xA5, 0x20, 0x01, 0x00]),
    "length over 32": bytes([0xA5, 0x21, 0x01, 0x00]),
    "A5 FF": bytes([0xA5, 0xFF]),
    "lone sync": bytes([0xA5]),
    "bad CRC": STEP_RAW[:-1] + bytes([STEP_RAW[-1] ^ 0x55]),
}


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
def test_the_client_parser_recovers_a_reply_behind_a_corrupted_frame(corruption):
    """The PC's side of the resynchronising scan: a reply behind each corruption is found, at once or once the line
    has been quiet for FRAME_GAP_S (an incomplete frame given up); the bytes after it are kept."""
    reply = Frame(MsgType.REPLY | MsgType.STATE, 4, bytes(26)).encode()
    parser = FrameParser()
    frames = parser.feed(CORRUPTIONS[corruption] + reply)
    frames += parser.expire(time.monotonic() + parser.gap_s)
    assert [(f.type, f.seq) for f in frames] == [(MsgType.REPLY | MsgType.STATE, 4)]
    assert parser.dropped_bytes >= 1 and not parser.buf
    assert parser.feed(reply) == frames  # and the parser goes on


def test_the_client_parser_waits_while_bytes_may_still_come():
    """A frame still arriving is not given up: expire drops nothing until the line has been quiet for gap_s."""
    reply = Frame(MsgType.REPLY | MsgType.STATE, 4, bytes(26)).encode()
    parser = FrameParser(gap_s=0.1)
    assert parser.feed(reply[:10]) == [] and parser.expire() == []
    assert [f.seq for f in parser.feed(reply[10:])] == [4]
    with pytest.raises(ProtocolError, match="gap_s"):
        FrameParser(gap_s=0.0)
