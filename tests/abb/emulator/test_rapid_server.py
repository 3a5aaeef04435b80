"""Pieces of the shipped RAPID server (assets/rapid/IRB120Server.mod, loaded with its serial channel module as on
a licence-free controller) executed by our RAPID interpreter: it parses, its CRC matches the protocol's on every
shared test vector, it decodes command payloads, and the state reply it builds decodes in Python to the state it
was given, with a reply type that fits a byte. (The full server loop runs in the controller emulator.)"""

from __future__ import annotations

import json
import math
from importlib import resources

import pytest

from maniskill_irb120.abb.emulator.rapid import Builtins, Interpreter, make_value
from maniskill_irb120.abb.protocol import FrameParser, MsgType, Status, decode_reply

ASSETS = resources.files("maniskill_irb120.assets").joinpath("rapid")
SOURCE = ASSETS.joinpath("IRB120Server.mod").read_text() + "\n" + ASSETS.joinpath("IRB120Serial.mod").read_text()
VECTORS = json.loads(ASSETS.joinpath("protocol_vectors.json").read_text())["frames"]


def server(joints_deg=(0.0,) * 6, tcp_mm=(350.0, 0.0, 250.0), quat=(0.0, 0.0, 1.0, 0.0), gripper=1) -> Interpreter:
    reg = Builtins()
    reg.add("CJointT", lambda **_: make_value("jointtarget", [list(joints_deg), [9e9] * 6]))
    reg.add("CRobT", lambda **_: make_value("robtarget", [list(tcp_mm), list(quat), [0, 0, 0, 0], [9e9] * 6]))
    reg.add("DOutput", lambda signal: gripper)
    return Interpreter(SOURCE, reg)


def load_rx(interp: Interpreter, raw: bytes) -> None:
    """The frame in the receive buffer as the parser leaves it: its sync at rx{frm}, here rx{1}."""
    rx = interp.get("rx")
    rx[: len(raw)] = raw
    interp.set("rx", rx)
    interp.set("frm", 1)


@pytest.mark.parametrize("vec", VECTORS, ids=lambda v: v["name"])
def test_rapid_crc_matches_every_vector(vec):
    interp = server()
    raw = bytes.fromhex(vec["hex"])
    load_rx(interp, raw)
    assert interp.call("Crc16Rx", 2, raw[1] + 3) == raw[-2] + 256 * raw[-1]


def test_rapid_decodes_a_tool_step():
    interp = server()
    raw = bytes.fromhex(next(v for v in VECTORS if v["name"].startswith("tool step: +1 cm"))["hex"])
    load_rx(interp, raw)
    # dx +1 cm, dy -0.5 cm, dz 0 (0.01 mm units), rot +10 deg (0.001 deg units)
    assert [interp.call("Int16At", i) for i in (4, 6, 8, 10)] == [1000, -500, 0, 10000]


@pytest.mark.parametrize("quat", [(0.0, 0.0, 1.0, 0.0), (0.5, 0.5, -0.5, 0.5), (0.1, -0.7, 0.1, 0.7)])
def test_rapid_reply_decodes_to_the_state(quat):
    n = math.sqrt(sum(v * v for v in quat))
    quat = tuple(v / n for v in quat)
    joints = (10.0, -20.5, 30.24, -140.0, 95.5, -380.0)  # multiples of the 0.02 deg unit
    interp = server(joints, gripper=1)
    # the reply carries the motion target (where the controller is taking the TCP), not CRobT
    interp.set("lastTarget", make_value("robtarget", [[412.35, -101.2, 88.05], list(quat), [0, 0, 0, 0], [9e9] * 6]))
    interp.set("refusal", 2)
    interp.set("status", 2)
    interp.call("BuildReply", MsgType.TOOL_STEP, 9)
    tx = bytes(int(b) for b in interp.get("tx")[: int(interp.get("txLen"))])
    (frame,) = FrameParser().feed(tx)
    assert frame.type == MsgType.REPLY | MsgType.TOOL_STEP and frame.seq == 9
    state = decode_reply(frame)
    assert [round(math.degrees(v), 2) for v in state.joints] == list(joints)
    assert [round(v * 1000, 2) for v in state.target_pos] == [412.35, -101.2, 88.05]
    assert abs(sum(a * b for a, b in zip(state.target_quat, quat))) > 1 - 1e-8
    assert state.gripper_open and state.status == Status.HELD and state.error == 2


@pytest.mark.parametrize("kind", [1, 2, 3, 4, 5, 6, 0x7F])
def test_rapid_reply_type_fits_a_byte(kind):
    """Finding 1's root: ``tx{3} := 128 + kind`` overflowed a byte for kinds >= 0x80; those frames are dropped
    before a reply is built, and the reply type is built so it cannot overflow whatever the kind."""
    interp = server()
    interp.call("BuildReply", kind, 3)
    assert int(interp.get("tx")[2]) == 0x80 | kind
