"""The shipped RAPID server module and the Python side agree on every number they share (the envelope,
the units): one set of limits on both sides of the wire. Its behaviour is tested by running it in the
controller emulator."""

from __future__ import annotations

import math
import re
from importlib import resources

import numpy as np
import pytest

from maniskill_irb120.abb import protocol
from maniskill_irb120.abb.envelope import CONTROL_PERIOD_S, WORKSPACE_HIGH, WORKSPACE_LOW, Envelope
from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT

MODULE = resources.files("maniskill_irb120.assets").joinpath("rapid", "IRB120Server.mod").read_text()


def const(name: str):
    m = re.search(rf"CONST\s+\w+\s+{name}(\{{\d+\}})?\s*:=\s*([^;]+);", MODULE, re.IGNORECASE)
    assert m, f"CONST {name} not found in IRB120Server.mod"
    value = m.group(2).strip()
    if value.startswith("["):
        return [float(v) for v in value.strip("[]").split(",")]
    return float(value) if re.fullmatch(r"-?[\d.]+", value) else value


def test_envelope_constants_match():
    assert const("STEP_POS_MM") == pytest.approx(TOOL_POS_LIMIT * 1000)
    assert const("STEP_ROT_DEG") == pytest.approx(math.degrees(TOOL_ROT_LIMIT))
    np.testing.assert_allclose(const("WORKSPACE_LOW"), np.asarray(WORKSPACE_LOW) * 1000)
    np.testing.assert_allclose(const("WORKSPACE_HIGH"), np.asarray(WORKSPACE_HIGH) * 1000)
    env = Envelope()
    np.testing.assert_allclose(const("JOINT_LOW"), np.degrees(env.joint_lower), atol=0.01)
    np.testing.assert_allclose(const("JOINT_HIGH"), np.degrees(env.joint_upper), atol=0.01)
    np.testing.assert_allclose(const("JOINT_STEP_DEG"), np.degrees(env._max_joint_step), atol=0.01)
    assert CONTROL_PERIOD_S == 0.05


def test_protocol_constants_match():
    assert const("SYNC") == protocol.SYNC and const("MAX_PAYLOAD") == protocol.MAX_PAYLOAD
    for t in ("STATE", "TOOL_STEP", "JOINTS", "GRIPPER", "STOP"):
        assert const(f"T_{t}") == protocol.MsgType[t]
    for s in protocol.Status:
        assert const(f"S_{s.name}") == s
    for e in protocol.ErrorCode:
        assert const(f"E_{e.name}") == e


def test_a_full_step_fits_one_control_period():
    speed = const("vStep")  # v_tcp mm/s, v_ori deg/s
    assert const("STEP_POS_MM") / speed[0] <= CONTROL_PERIOD_S
    assert const("STEP_ROT_DEG") / speed[1] <= CONTROL_PERIOD_S
