"""Jogging the emulated robot (our RAPID server on the controller emulator, over TCP) with synthetic device
streams: hold-to-run moves it, releasing the dead-man stops it within one control period, and a step the
envelope refuses leaves it held, says why, and the jogger stays usable."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")

from maniskill_irb120.abb.client import ABBRobot  # noqa: E402
from maniskill_irb120.abb.emulator.controller import ControllerEmulator  # noqa: E402
from maniskill_irb120.abb.envelope import Envelope  # noqa: E402
from maniskill_irb120.abb.protocol import Status  # noqa: E402
from maniskill_irb120.teleop.devices import Command, Scripted  # noqa: E402
from maniskill_irb120.teleop.jog import JogConfig, Jogger  # noqa: E402

PERIOD = 0.05
UP = Command(translation=(0.0, 0.0, 1.0), deadman=True)
DOWN = Command(translation=(0.0, 0.0, -1.0), deadman=True)
RELEASED = Command(translation=(0.0, 0.0, 1.0), deadman=False)  # motion asked, dead-man let go


@pytest.fixture(scope="module")
def emulator():
    emu = ControllerEmulator("tcp")
    url = emu.start()
    yield emu, url
    emu.stop()
    assert emu.error is None, emu.error


def tcp(robot: ABBRobot, state=None) -> np.ndarray:
    return robot.envelope.tcp_pose((state or robot.state()).joints)[:3, 3]


def drive(jogger: Jogger, periods: int) -> list[str]:
    """``periods`` control periods in real time (the emulated robot moves in real time)."""
    out = []
    for _ in range(periods):
        t0 = time.monotonic()
        out.append(jogger.step())
        time.sleep(max(0.0, PERIOD - (time.monotonic() - t0)))
    return out


def test_releasing_the_deadman_stops_the_robot_within_one_period(emulator):
    _, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as robot:
        start = tcp(robot)
        said = []
        device = Scripted([UP] * 8 + [RELEASED] * 6)
        jogger = Jogger(robot, device, JogConfig(frame="world", step_mm=2.0, period_s=PERIOD), say=said.append)
        assert drive(jogger, 8) == ["moved"] * 8
        t_release = time.monotonic()
        assert jogger.step() == "stopped"  # the first period that sees the release sends STOP
        stopped = robot.last_state
        assert time.monotonic() - t_release < PERIOD
        assert stopped.status == Status.HELD and said == ["stopped: dead-man released"]
        at_stop = tcp(robot, stopped)
        assert drive(jogger, 5) == ["idle"] * 5  # nothing more is sent until the dead-man is held again
        after = tcp(robot)
        np.testing.assert_allclose(after, at_stop, atol=3e-4)  # held where it stopped (0.02 deg joint quanta)
        moved = at_stop - start
        assert 0.004 < moved[2] <= 8 * 0.002 + 3e-4  # up, at most 2 mm a period: the dry-run speed
        np.testing.assert_allclose(moved[:2], 0.0, atol=5e-4)  # world frame: straight up
        assert jogger.steps == 8 and jogger.stops == 1


def test_a_refused_step_holds_the_robot_says_why_and_stays_usable(emulator):
    _, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as probe:
        z0 = tcp(probe)[2]
    # a box whose ceiling is 3 mm above the TCP (+ the envelope's 1 mm margin): the second step up is refused
    envelope = Envelope(workspace_high=(0.60, 0.32, z0 + 0.004))
    with ABBRobot.connect(url, timeout=1.0, envelope=envelope) as robot:
        said = []
        device = Scripted([UP] * 6 + [DOWN] * 2)
        jogger = Jogger(robot, device, JogConfig(step_mm=2.0, period_s=PERIOD), say=said.append)
        got = drive(jogger, 6)
        assert got[0] == "moved" and set(got[1:]) == {"refused"}
        held = tcp(robot)
        assert held[2] <= z0 + 0.003 and robot.state().status in (Status.HELD, Status.IDLE)
        assert len(said) == 1 and "refused by the safety envelope (workspace)" in said[0]  # once, with the limit
        time.sleep(0.1)
        np.testing.assert_allclose(tcp(robot), held, atol=3e-4)  # the key still pressed: nothing moved
        assert drive(jogger, 2) == ["moved", "moved"]  # another direction goes on
        assert jogger.step() == "quit"


def test_gripper_toggle_and_the_loop_stop_the_robot_on_quit(emulator):
    emu, url = emulator
    with ABBRobot.connect(url, timeout=1.0) as robot:
        # a toggle without the dead-man does nothing (the gripper moves too); with it, the gripper closes
        device = Scripted([Command(gripper_toggle=True), Command(gripper_toggle=True, deadman=True), DOWN, DOWN])
        clock = iter(np.arange(0, 10, 0.01))
        said: list[str] = []
        jogger = Jogger(robot, device, JogConfig(period_s=PERIOD), say=said.append)
        result = jogger.run(clock=lambda: float(next(clock)), sleep=time.sleep)
        assert said[0] == "gripper not toggled: hold the dead-man" and said[1] == "gripper closed"
        assert result["steps"] == 2 and emu.signals["doGripperOpen"] == 0
        assert robot.last_state.status == Status.HELD  # the loop's exit sent STOP
        assert robot.set_gripper(True).gripper_open


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="step_mm"):
        JogConfig(step_mm=15.0)
    with pytest.raises(ValueError, match="frame"):
        JogConfig(frame="base")


def test_the_teleop_command_jogs_the_emulator(capsys):
    from maniskill_irb120.cli import _jog

    assert _jog("emulator", Scripted([UP] * 3 + [Command()]), "world", 2.0, 1.0) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["steps"] == 3 and result["robot"].startswith("tcp://127.0.0.1:")
