"""The shipped RAPID server modules and the Python side agree on every number they share (the envelope,
the units): one set of limits on both sides of the wire; each module names only the RobotWare options it is
meant to need. Their behaviour is tested by running them in the controller emulator."""

from __future__ import annotations

import math
import re
from importlib import resources

import numpy as np
import pytest

from maniskill_irb120.abb import protocol
from maniskill_irb120.abb.envelope import CONTROL_PERIOD_S, WORKSPACE_HIGH, WORKSPACE_LOW, Envelope
from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT

RAPID = resources.files("maniskill_irb120.assets").joinpath("rapid")
MODULE = RAPID.joinpath("IRB120Server.mod").read_text()
FILES = ("IRB120Server.mod", "IRB120Serial.mod", "IRB120Socket.mod", "IRB120Zone.sys")


def const(name: str, module: str = MODULE):
    m = re.search(rf"CONST\s+\w+\s+{name}(\{{\d+\}})?\s*:=\s*([^;]+);", module, re.IGNORECASE)
    assert m, f"CONST {name} not found"
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
    speed = const("vFull")  # v_tcp mm/s, v_ori deg/s: the speed with SPEED_PERCENT at 100
    assert const("STEP_POS_MM") / speed[0] <= CONTROL_PERIOD_S
    assert const("STEP_ROT_DEG") / speed[1] <= CONTROL_PERIOD_S
    assert 0 < const("SPEED_PERCENT") <= 100  # first runs: a fraction of it (docs/real_robot.md)


def code(name: str) -> str:
    """A module's text without its comments."""
    return re.sub(r"!.*", "", RAPID.joinpath(name).read_text())


SOCKET_API = r"\b(socketdev|Socket\w+|ERR_SOCK_\w+)\b"
WORLD_ZONES = r"\b(WZ\w+|wztemporary|wzstationary|shapedata)\b"


@pytest.mark.parametrize(
    "name, socket_api, world_zones",
    [
        ("IRB120Server.mod", False, False),
        ("IRB120Serial.mod", False, False),
        ("IRB120Socket.mod", True, False),
        ("IRB120Zone.sys", False, True),
    ],
)
def test_each_file_names_only_its_options(name, socket_api, world_zones):
    """A controller resolves every name when a module loads: the socket API needs 616-1 or 672-1, world zones
    608-1. Core + serial must load on a controller with neither."""
    text = code(name)
    assert bool(re.search(SOCKET_API, text, re.IGNORECASE)) == socket_api
    assert bool(re.search(WORLD_ZONES, text, re.IGNORECASE)) == world_zones


HOOKS = {
    "irb120chanopen",
    "irb120chanread",
    "irb120chanwrite",
    "irb120channewpeer",
    "irb120chanreopen",
    "irb120chanclose",
}


def global_names(name: str) -> set[str]:
    """Module-level data and routines not declared LOCAL."""
    text = code(name)
    routines = re.findall(r"^\s*(?!LOCAL)(?:PROC|FUNC\s+\w+|TRAP)\s+(\w+)", text, re.IGNORECASE | re.MULTILINE)
    data = re.findall(r"^\s{4}(?!LOCAL)(?:VAR|PERS|CONST)\s+\w+\s+(\w+)", text, re.IGNORECASE | re.MULTILINE)
    return {n.lower() for n in routines + data}


def test_only_the_entry_and_the_hooks_are_global():
    """Names are global to a task unless LOCAL: beside the stock MainModule (its main) and other modules, ours add
    one entry routine, its RESTART event routine, the channel hooks and the zone's event routine, nothing else."""
    assert global_names("IRB120Server.mod") == {"irb120server", "irb120serverrestart"}
    assert global_names("IRB120Serial.mod") == HOOKS
    assert global_names("IRB120Socket.mod") == HOOKS
    assert global_names("IRB120Zone.sys") == {"irb120zonepoweron"}
    assert not re.search(r"\bPROC\s+main\b", "".join(code(f) for f in FILES), re.IGNORECASE)


def test_world_zone_lies_just_outside_the_workspace():
    zone = RAPID.joinpath("IRB120Zone.sys").read_text()
    margin = const("ZONE_MARGIN_MM", zone)
    np.testing.assert_allclose(const("ZONE_LOW", zone), np.asarray(const("WORKSPACE_LOW")) - margin)
    np.testing.assert_allclose(const("ZONE_HIGH", zone), np.asarray(const("WORKSPACE_HIGH")) + margin)
