"""What every teleoperation device gives the loops that drive a sim or a robot: one :class:`Command` per poll.

A device is anything with ``poll() -> Command`` and ``close()`` (the :class:`Device` protocol), so a new device
is one small class that turns its own events into a Command. The sim loop (``teleop.sim``) and the robot jog
loop (``teleop.jog``) poll once per control period and never see a device's events themselves.

This module and the device drivers import neither ManiSkill nor SAPIEN (``tests/test_layers.py``): a robot PC
jogs the robot with them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import Protocol, runtime_checkable

DEVICES = ("keyboard", "spacemouse", "gamepad")
BUTTON_ACTIONS = ("gripper_toggle", "save", "discard", "reset", "quit")
"""what a device button may do (the edge flags of :class:`Command`)"""


@dataclass(frozen=True)
class Command:
    """One control period's worth of operator input. Motion is normalised: each component in [-1, 1] is a
    fraction of the loop's full step along that axis of the chosen frame (tool or world)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """x, y, z in [-1, 1]: along the frame's axes (the tool frame's x is the approach axis)"""
    yaw: float = 0.0
    """[-1, 1]: rotation about the tool's approach axis, the action space's only rotation"""
    deadman: bool = False
    """the enabling input is held: the jog loop moves the robot only while it is, and stops it when it is not"""
    gripper_toggle: bool = False
    """open a closed gripper, close an open one (an edge: reported once per press)"""
    save: bool = False
    """keep the episode in the demo file and start the next seed"""
    reset: bool = False
    """drop the episode and restart the same seed (try again)"""
    discard: bool = False
    """drop the episode and go on to the next seed"""
    quit: bool = False
    """end the session (the episode in progress is dropped; the robot is stopped)"""

    def __post_init__(self):
        values = (*self.translation, self.yaw)
        if len(self.translation) != 3 or not all(isinstance(v, (int, float)) and -1.0 <= v <= 1.0 for v in values):
            raise ValueError(f"a command's translation is 3 numbers and its yaw 1, all in [-1, 1]; got {values}")

    @property
    def moving(self) -> bool:
        return any(self.translation) or self.yaw != 0.0


IDLE = Command()


@runtime_checkable
class Device(Protocol):
    """A teleoperation input: ``poll`` returns what the operator asks for now, without blocking."""

    def poll(self) -> Command: ...

    def close(self) -> None: ...


def clip_unit(v: float) -> float:
    return max(-1.0, min(1.0, float(v)))


def deadzone(v: float, dz: float) -> float:
    """0 inside ``±dz``; outside, rescaled so the output still spans (0, 1] (no jump at the edge)."""
    v = clip_unit(v)
    if abs(v) <= dz:
        return 0.0
    return (abs(v) - dz) / (1.0 - dz) * (1.0 if v > 0 else -1.0)


def merge(first: Command, second: Command) -> Command:
    """Two devices polled together (a SpaceMouse for motion, the terminal for save / discard / quit): motion and
    the dead-man from whichever device moves (the first if both do), every key edge from either."""
    mover = first if first.moving or not second.moving else second
    return replace(
        mover,
        gripper_toggle=first.gripper_toggle or second.gripper_toggle,
        save=first.save or second.save,
        reset=first.reset or second.reset,
        discard=first.discard or second.discard,
        quit=first.quit or second.quit,
    )


class Merged:
    """Polls several devices each period as one (see :func:`merge`); closes them all."""

    def __init__(self, *devices: Device):
        if not devices:
            raise ValueError("Merged needs at least one device")
        self.devices = devices

    def poll(self) -> Command:
        out = self.devices[0].poll()
        for d in self.devices[1:]:
            out = merge(out, d.poll())
        return out

    def close(self) -> None:
        for d in self.devices:
            d.close()


@dataclass
class Scripted:
    """A recorded or synthetic command stream, one command per poll, then ``after`` forever: how the loops are
    tested without hardware, and how a session can be replayed against the emulator."""

    commands: Iterable[Command]
    after: Command = field(default_factory=lambda: Command(quit=True))

    def __post_init__(self):
        self._it: Iterator[Command] = iter(self.commands)
        self.polls = 0

    def poll(self) -> Command:
        self.polls += 1
        return next(self._it, self.after)

    def close(self) -> None:
        pass


def open_device(name: str, **kwargs) -> Device:
    """The named device (``keyboard``, ``spacemouse``, ``gamepad``) with its driver's keyword arguments."""
    if name == "keyboard":
        from maniskill_irb120.teleop.keyboard import Keyboard

        return Keyboard(**kwargs)
    if name == "spacemouse":
        from maniskill_irb120.teleop.spacemouse import SpaceMouse

        return SpaceMouse(**kwargs)
    if name == "gamepad":
        from maniskill_irb120.teleop.gamepad import Gamepad

        return Gamepad(**kwargs)
    raise ValueError(f"unknown device {name!r}; use one of {DEVICES}")
