"""A gamepad through the Linux joystick API (``/dev/input/js*``; no library): each event is 8 bytes,
``struct js_event {u32 time_ms; s16 value; u8 type; u8 number}`` (``struct 'IhBB'``), type 1 a button, 2 an axis,
0x80 or-ed in for the state the kernel reports when the device is opened.

A gamepad reports releases: the dead-man is a shoulder button held (RB / R1 by default), so letting it go stops a
jogged robot at the next control period. Layouts: ``xbox`` (the xpad driver: Xbox 360 / One and most clones) and
``dualsense`` (the hid-playstation driver); another pad is a :class:`GamepadMap` of its axis and button numbers
(``jstest /dev/input/js0`` shows them).
"""

from __future__ import annotations

import errno
import os
import struct
from dataclasses import dataclass, field

from maniskill_irb120.teleop.devices import BUTTON_ACTIONS, Command, deadzone

EVENT = struct.Struct("<IhBB")
JS_BUTTON, JS_AXIS, JS_INIT = 0x01, 0x02, 0x80
AXIS_MAX = 32767.0


@dataclass(frozen=True)
class GamepadMap:
    """Which axis and button does what. An axis is (number, sign): the sign makes pushing the stick away from
    the operator +x, left +y, up +z and left (counter-clockwise) +yaw."""

    x: tuple[int, float] = (1, -1.0)
    """left stick up/down (up reads negative)"""
    y: tuple[int, float] = (0, -1.0)
    """left stick left/right"""
    z: tuple[int, float] = (4, -1.0)
    """right stick up/down"""
    yaw: tuple[int, float] = (3, -1.0)
    """right stick left/right"""
    deadman_button: int | None = 5
    """held to move (RB / R1); None: any stick deflection counts as held"""
    buttons: dict[int, str] = field(
        default_factory=lambda: {0: "gripper_toggle", 7: "save", 6: "discard", 3: "reset", 8: "quit"}
    )
    """button number -> action: A gripper, Start save, Back discard, Y reset, Guide quit"""
    dead_zone: float = 0.15
    """stick fraction read as zero (sticks rarely centre exactly)"""

    def __post_init__(self):
        bad = sorted(set(self.buttons.values()) - set(BUTTON_ACTIONS))
        if bad:
            raise ValueError(f"unknown button actions {bad}; use {BUTTON_ACTIONS}")
        if not 0 <= self.dead_zone < 1:
            raise ValueError(f"dead_zone must be in [0, 1), got {self.dead_zone}")


LAYOUTS = {
    "xbox": GamepadMap(),
    # hid-playstation: 0 cross, 2 triangle, 5 R1, 8 create, 9 options, 10 PS
    "dualsense": GamepadMap(buttons={0: "gripper_toggle", 9: "save", 8: "discard", 2: "reset", 10: "quit"}),
}


class JoystickEvents:
    """The pad's state from its event bytes: ``feed(data)`` (any split, partial events are kept for the next
    call), ``command()`` for the state now."""

    def __init__(self, mapping: GamepadMap):
        self.map = mapping
        self.axes: dict[int, float] = {}
        self.held: set[int] = set()
        self._edges: set[str] = set()
        self._rest = b""

    def feed(self, data: bytes) -> None:
        data = self._rest + data
        n = len(data) // EVENT.size * EVENT.size
        self._rest = data[n:]
        for _, value, kind, number in EVENT.iter_unpack(data[:n]):
            if kind & ~JS_INIT == JS_AXIS:
                self.axes[number] = value / AXIS_MAX
            elif kind & ~JS_INIT == JS_BUTTON:
                if value and number not in self.held and not kind & JS_INIT and number in self.map.buttons:
                    self._edges.add(self.map.buttons[number])  # a button already down when opened is no press
                (self.held.add if value else self.held.discard)(number)

    def _axis(self, spec: tuple[int, float]) -> float:
        number, sign = spec
        return deadzone(sign * self.axes.get(number, 0.0), self.map.dead_zone)

    def command(self) -> Command:
        t = (self._axis(self.map.x), self._axis(self.map.y), self._axis(self.map.z))
        yaw = self._axis(self.map.yaw)
        if self.map.deadman_button is None:
            deadman = any(t) or yaw != 0.0
        else:
            deadman = self.map.deadman_button in self.held
        edges = {e: True for e in self._edges}
        self._edges.clear()
        return Command(translation=t, yaw=yaw, deadman=deadman, **edges)


class Gamepad:
    """A joystick device node as a :class:`~maniskill_irb120.teleop.devices.Device` (read without blocking)."""

    def __init__(self, path: str = "/dev/input/js0", layout: str | GamepadMap = "xbox"):
        if isinstance(layout, str):
            if layout not in LAYOUTS:
                raise ValueError(f"unknown gamepad layout {layout!r}; use one of {sorted(LAYOUTS)} or a GamepadMap")
            layout = LAYOUTS[layout]
        try:
            self.fd: int | None = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as e:
            raise RuntimeError(
                f"cannot open the gamepad at {path}: {e.strerror} (is it plugged in? ls /dev/input/js*)"
            ) from None
        self.path, self.events = path, JoystickEvents(layout)

    def poll(self) -> Command:
        if self.fd is None:
            raise RuntimeError("the gamepad device is closed")
        while True:
            try:
                data = os.read(self.fd, EVENT.size * 64)
            except BlockingIOError:
                break
            except OSError as e:
                if e.errno == errno.ENODEV:
                    raise RuntimeError(f"the gamepad at {self.path} was unplugged") from None
                raise
            if not data:
                break
            self.events.feed(data)
        return self.events.command()

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
