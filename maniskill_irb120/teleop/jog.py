"""Jogging a robot with a teleoperation device, through ``ABBRobot`` (the emulator or a real IRC5): the way an
integrator moves the arm before trusting a policy with it.

Hold-to-run: each control period the device is polled once; while its dead-man is held and it asks for motion,
one small tool step is sent (``ABBRobot.move_tool``, which checks it against the safety ``Envelope`` first). The
first period that finds the dead-man released sends STOP (the controller stops and clears its path) and then
nothing more until the dead-man is held again; so a device that reports releases (SpaceMouse, gamepad) stops the
robot within one period. The terminal keyboard reports no releases (see ``teleop.keyboard``).

A step the envelope (or the controller) refuses is not sent: the robot is stopped where it is, the reason is
printed once, and the jogger stays usable: motion in another direction goes on at the next period.

The controller's own watchdog is the last line: while the robot moves, a PC that falls silent for 0.5 s has its
motion stopped on the controller (docs/protocol.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from maniskill_irb120.abb.client import ABBRobot, ControllerRefused, RobotError
from maniskill_irb120.abb.envelope import CONTROL_PERIOD_S, EnvelopeError
from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT, world_to_tool
from maniskill_irb120.teleop.devices import Command, Device

FRAMES = ("tool", "world")


@dataclass(frozen=True)
class JogConfig:
    frame: Literal["tool", "world"] = "world"
    """axes the device's x/y/z move along: the robot base's (world) or the TCP's (tool; x is the approach axis)"""
    step_mm: float = 2.0
    """mm the TCP moves per control period at full deflection: 40 mm/s at 20 Hz, a first dry run's pace"""
    step_deg: float = 1.0
    """degrees about the approach axis per control period at full deflection (20 deg/s at 20 Hz)"""
    period_s: float = CONTROL_PERIOD_S
    """the control period: one poll and at most one command per period"""

    def __post_init__(self):
        if self.frame not in FRAMES:
            raise ValueError(f"frame={self.frame!r}: use one of {FRAMES}")
        if not 0 < self.step_mm <= TOOL_POS_LIMIT * 1000:
            raise ValueError(f"step_mm must be in (0, {TOOL_POS_LIMIT * 1000:g}] (the step limit), got {self.step_mm}")
        if not 0 < self.step_deg <= math.degrees(TOOL_ROT_LIMIT):
            raise ValueError(f"step_deg must be in (0, {math.degrees(TOOL_ROT_LIMIT):g}], got {self.step_deg}")
        if not 0 < self.period_s <= 0.25:
            raise ValueError(f"period_s must be in (0, 0.25] s (the watchdog is 0.5 s), got {self.period_s}")


class Jogger:
    """One robot, one device. ``step()`` is one control period; ``run()`` paces it until the device quits.
    ``say``: where the operator reads what happened (a refusal's reason, a stop)."""

    def __init__(self, robot: ABBRobot, device: Device, cfg: JogConfig = JogConfig(), say: Callable = print):
        self.robot, self.device, self.cfg, self.say = robot, device, cfg, say
        state = robot.last_state or robot.state()
        self.gripper_open = bool(state.gripper_open)
        self.moving = False
        self.refusal: str | None = None
        self.steps = self.refused = self.stops = 0

    def action(self, cmd: Command) -> np.ndarray:
        """The normalised tool action (5,) for ``cmd`` at the configured speeds, in the configured frame."""
        t = np.asarray(cmd.translation, dtype=np.float64) * (self.cfg.step_mm / 1000.0 / TOOL_POS_LIMIT)
        yaw = cmd.yaw * math.radians(self.cfg.step_deg) / TOOL_ROT_LIMIT
        a = np.r_[t, yaw, 1.0 if self.gripper_open else -1.0]
        if self.cfg.frame == "world":
            joints = (self.robot.last_state or self.robot.state()).joints
            rot = torch.as_tensor(self.robot.envelope.tcp_pose(joints)[:3, :3])
            a = world_to_tool(torch.as_tensor(a)[None], rot[None])[0].numpy()
        return a

    def step(self) -> str:
        """Poll the device once and act: returns what happened (moved, refused, stopped, idle, quit)."""
        cmd = self.device.poll()
        if cmd.quit:
            self.halt()
            return "quit"
        if cmd.gripper_toggle and not cmd.deadman:  # the gripper moves too: it needs the dead-man like the arm
            self.say("gripper not toggled: hold the dead-man")
        elif cmd.gripper_toggle:
            self.gripper_open = not self.gripper_open
            self.robot.set_gripper(self.gripper_open)
            self.say(f"gripper {'open' if self.gripper_open else 'closed'}")
        if cmd.deadman and cmd.moving:
            try:
                self.robot.move_tool(self.action(cmd))
            except (EnvelopeError, ControllerRefused) as e:
                self.halt()
                self.refused += 1
                # once per limit, not 20 times a second (the numbers in the message move as the robot settles)
                reason = e.limit if isinstance(e, EnvelopeError) else f"controller {int(e.state.error)}"
                if reason != self.refusal:
                    self.say(f"held: {e}")
                    self.refusal = reason
                return "refused"
            self.moving, self.refusal = True, None
            self.steps += 1
            return "moved"
        if self.moving:
            self.halt()
            self.say("stopped: dead-man released")
            return "stopped"
        return "idle"

    def halt(self) -> None:
        """STOP once if a motion was commanded since the last one (the robot holds where it is)."""
        if self.moving:
            self.robot.stop()
            self.stops += 1
            self.moving = False

    def run(self, clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep) -> dict:
        """Step once per period until the device quits; the robot is stopped however this ends."""
        t_next = clock()
        try:
            while self.step() != "quit":
                t_next += self.cfg.period_s
                late = clock() - t_next
                if late > 0:  # a slow period: keep the rate, do not bunch commands up to catch up
                    t_next += math.ceil(late / self.cfg.period_s) * self.cfg.period_s
                sleep(max(0.0, t_next - clock()))
        finally:
            try:
                self.robot.stop()  # unconditionally, however the loop ended
                self.stops += 1
            except RobotError:
                pass  # the connection is gone: the controller's watchdog stops a moving robot
            self.moving = False
        return dict(steps=self.steps, refused=self.refused, stops=self.stops)
