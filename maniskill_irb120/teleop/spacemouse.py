"""A 3Dconnexion SpaceMouse read through ``hidapi`` (``pip install hidapi``; the ``teleop`` extra), its HID
reports parsed here so the parser is tested on synthetic reports without the device.

The reports (3Dconnexion's HID format, as spacenavd and pyspacemouse read it): report 1 carries the translation
as three little-endian int16 (x right, y toward the operator, z down), and on newer devices (SpaceMouse Compact,
Wireless, Enterprise) the rotation about those axes right after it; older ones (SpaceNavigator, SpaceMouse Pro)
send the rotation as report 2. Report 3 is the buttons, one bit each. A full push reads about ±350.

The puck springs back when let go and the device then reports zeros, a real release: the dead-man is "the puck
is deflected past the dead zone", so letting go stops a jogged robot at the next control period. Linux needs
read access to the hidraw node (a udev rule such as ``KERNEL=="hidraw*", ATTRS{idVendor}=="256f",
MODE="0666"``; 046d for older devices).
"""

from __future__ import annotations

import struct
from typing import Any

from maniskill_irb120.teleop.devices import BUTTON_ACTIONS, Command, deadzone

KNOWN_DEVICES = {
    (0x046D, 0xC626): "SpaceNavigator",
    (0x046D, 0xC627): "SpaceExplorer",
    (0x046D, 0xC628): "SpaceNavigator for Notebooks",
    (0x046D, 0xC62B): "SpaceMouse Pro",
    (0x256F, 0xC62E): "SpaceMouse Wireless (cable)",
    (0x256F, 0xC62F): "SpaceMouse Wireless (receiver)",
    (0x256F, 0xC631): "SpaceMouse Pro Wireless (cable)",
    (0x256F, 0xC632): "SpaceMouse Pro Wireless (receiver)",
    (0x256F, 0xC633): "SpaceMouse Enterprise",
    (0x256F, 0xC635): "SpaceMouse Compact",
    (0x256F, 0xC652): "3Dconnexion Universal Receiver",
}
VENDOR_3DCONNEXION = 0x256F


class SpaceMouseReports:
    """The device's state from its raw reports: ``feed(report)`` for each report read (bytes, report id
    first), ``command()`` for the state now. Axis values in device counts (about ±350 at full push)."""

    def __init__(self, full_scale: float = 350.0, dead_zone: float = 0.1, buttons: tuple[str | None, ...] = ()):
        if not full_scale > 0 or not 0 <= dead_zone < 1:
            raise ValueError(f"full_scale must be > 0 and dead_zone in [0, 1), got {full_scale}, {dead_zone}")
        bad = [b for b in buttons if b is not None and b not in BUTTON_ACTIONS]
        if bad:
            raise ValueError(f"unknown button actions {bad}; use {BUTTON_ACTIONS} or None")
        self.full_scale, self.dead_zone, self.buttons = full_scale, dead_zone, tuple(buttons)
        self.translation = [0, 0, 0]
        self.rotation = [0, 0, 0]
        self.pressed = 0
        self._edges: set[str] = set()

    def feed(self, report: bytes | list[int]) -> None:
        report = bytes(report)
        if not report:
            return
        rid, body = report[0], report[1:]
        if rid == 1 and len(body) >= 6:
            self.translation = list(struct.unpack_from("<3h", body))
            if len(body) >= 12:
                self.rotation = list(struct.unpack_from("<3h", body, 6))
        elif rid == 2 and len(body) >= 6:
            self.rotation = list(struct.unpack_from("<3h", body))
        elif rid == 3 and body:
            pressed = int.from_bytes(body[:4], "little")
            for i, action in enumerate(self.buttons):
                if action and pressed & (1 << i) and not self.pressed & (1 << i):
                    self._edges.add(action)
            self.pressed = pressed

    def command(self) -> Command:
        """Forward (away from the operator) is +x, left +y, up +z, a counter-clockwise twist seen from above
        +yaw: the device's x right / y toward the operator / z down turned into that right-handed frame."""
        x, y, z = (v / self.full_scale for v in self.translation)
        rz = self.rotation[2] / self.full_scale
        t = (deadzone(-y, self.dead_zone), deadzone(-x, self.dead_zone), deadzone(-z, self.dead_zone))
        yaw = deadzone(-rz, self.dead_zone)
        edges = {e: True for e in self._edges}
        self._edges.clear()
        return Command(translation=t, yaw=yaw, deadman=any(t) or yaw != 0.0, **edges)


def find_spacemouse(hid_module: Any) -> dict:
    """hidapi's enumeration entry of the first SpaceMouse plugged in; a clear error when there is none."""
    found = [
        d
        for d in hid_module.enumerate()
        if (d["vendor_id"], d["product_id"]) in KNOWN_DEVICES or d["vendor_id"] == VENDOR_3DCONNEXION
    ]
    if not found:
        raise RuntimeError(
            "no 3Dconnexion SpaceMouse found over HID (is it plugged in, and may this user read its /dev/hidraw* "
            "node? see maniskill_irb120/teleop/spacemouse.py for a udev rule)"
        )
    return found[0]


class SpaceMouse:
    """A SpaceMouse as a :class:`~maniskill_irb120.teleop.devices.Device`: reads every report pending at each
    poll. ``buttons``: what each button does, left first (the two-button models: gripper, save).
    ``device``: an opened hidapi device (tests pass a fake); by default the first SpaceMouse found."""

    def __init__(
        self,
        full_scale: float = 350.0,
        dead_zone: float = 0.1,
        buttons: tuple[str | None, ...] = ("gripper_toggle", "save"),
        device: Any = None,
    ):
        self.reports = SpaceMouseReports(full_scale, dead_zone, buttons)
        if device is None:
            try:
                import hid  # the hidapi package
            except ImportError:
                raise RuntimeError(
                    "the SpaceMouse needs hidapi: pip install hidapi (or pip install 'maniskill-irb120[teleop]')"
                ) from None
            info = find_spacemouse(hid)
            device = hid.device()
            device.open_path(info["path"])
            device.set_nonblocking(True)
        self.device = device

    def poll(self) -> Command:
        if self.device is None:
            raise RuntimeError("the SpaceMouse device is closed")
        for _ in range(256):  # everything pending; the device sends at most ~120 reports/s
            report = self.device.read(64)
            if not report:
                break
            self.reports.feed(report)
        return self.reports.command()

    def close(self) -> None:
        if self.device is not None:
            self.device.close()
            self.device = None
