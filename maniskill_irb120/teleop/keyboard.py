"""The keyboard of the terminal the command runs in (works over SSH, needs no display): the terminal is put in
cbreak mode (keys arrive one by one, unechoed; Ctrl-C still interrupts) and read without blocking.

A terminal reports key presses and the autorepeat of a held key, never a release. So "held" means: a jog key
keeps its motion alive for ``hold_s`` after its newest press or repeat event, and a poll that finds none that
fresh reports no motion and no dead-man. Two consequences an operator feels:

* a key held down moves once, pauses through the terminal's initial autorepeat delay (250–660 ms: X11 660,
  GNOME 500, macOS ~250 by default), then moves continuously, provided the repeat interval (X11 40 ms, GNOME
  30 ms) is shorter than ``hold_s``;
* after the key is let go the motion goes on for at most ``hold_s``, and the jog loop stops the robot at its next
  period: within ``hold_s`` + one control period, not within one period as with the SpaceMouse or a gamepad,
  which report real releases.
"""

from __future__ import annotations

import os
import select
import sys
import termios
import time
import tty
from collections.abc import Callable

from maniskill_irb120.teleop.devices import Command, clip_unit

MOTION_KEYS: dict[str, tuple[int, float]] = {
    "w": (0, 1.0), "s": (0, -1.0), "up": (0, 1.0), "down": (0, -1.0),
    "a": (1, 1.0), "d": (1, -1.0), "left": (1, 1.0), "right": (1, -1.0),
    "r": (2, 1.0), "f": (2, -1.0),
    "z": (3, 1.0), "x": (3, -1.0),
}  # fmt: skip
"""key -> (axis: x, y, z, yaw; sign)"""
EDGE_KEYS = {
    " ": "gripper_toggle",
    "\r": "save",
    "\n": "save",
    "\x7f": "reset",  # Backspace
    "\x08": "reset",  # Ctrl-H, what some terminals send for Backspace
    "n": "discard",
    "q": "quit",
    "esc": "quit",
}
ARROWS = {"A": "up", "B": "down", "C": "right", "D": "left"}
HELP = (
    "keys: w/s x+-  a/d y+-  r/f z+-  z/x yaw+-  (arrows: x/y)  space gripper  "
    "Enter save  Backspace reset  n discard  q quit"
)


def parse_keys(data: bytes) -> list[str]:
    """Key names in ``data``: characters as themselves, arrow escape sequences (``ESC [ A`` or ``ESC O A``) as
    up/down/right/left, a lone ESC as ``esc``; other escape sequences (function keys) are skipped."""
    text = data.decode("utf-8", errors="replace")
    out, i = [], 0
    while i < len(text):
        c = text[i]
        if c != "\x1b":
            out.append(c.lower() if c.isalpha() else c)
            i += 1
            continue
        if i + 1 < len(text) and text[i + 1] in "[O":
            j = i + 2
            while j < len(text) and not ("@" <= text[j] <= "~"):  # parameters up to the final byte
                j += 1
            if j < len(text) and text[j] in ARROWS:
                out.append(ARROWS[text[j]])
            i = j + 1
        else:
            out.append("esc")
            i += 1
    return out


class Keyboard:
    """The terminal on ``fd`` (standard input unless given) as a :class:`~maniskill_irb120.teleop.devices.Device`.
    ``clock``: seconds, monotonic (tests pass a fake one)."""

    def __init__(self, fd: int | None = None, hold_s: float = 0.1, clock: Callable[[], float] = time.monotonic):
        fd = sys.stdin.fileno() if fd is None else fd
        if not os.isatty(fd):
            raise ValueError(
                "the keyboard device reads a terminal and standard input is not one: run the command in a terminal "
                "(over SSH: ssh -t), or pick --device spacemouse / gamepad"
            )
        if not hold_s > 0:
            raise ValueError(f"hold_s must be > 0 s, got {hold_s}")
        self.fd, self.hold_s, self.clock = fd, hold_s, clock
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        self._motion = (0.0, 0.0, 0.0, 0.0)
        self._last_event = -float("inf")

    def read_keys(self) -> list[str]:
        data = b""
        while self.fd is not None and select.select([self.fd], [], [], 0)[0]:
            chunk = os.read(self.fd, 1024)
            if not chunk:
                break
            data += chunk
        return parse_keys(data)

    def poll(self) -> Command:
        if self.fd is None:
            raise RuntimeError("the keyboard device is closed")
        keys = self.read_keys()
        now = self.clock()
        motion = [0.0] * 4
        edges: dict[str, bool] = {}
        for k in keys:
            if k in MOTION_KEYS:
                axis, sign = MOTION_KEYS[k]
                motion[axis] = clip_unit(motion[axis] + sign)
            elif k in EDGE_KEYS:
                edges[EDGE_KEYS[k]] = True
        if any(k in MOTION_KEYS for k in keys):
            self._motion, self._last_event = tuple(motion), now
        elif now - self._last_event > self.hold_s:
            self._motion = (0.0, 0.0, 0.0, 0.0)
        held = any(self._motion)
        return Command(translation=self._motion[:3], yaw=self._motion[3], deadman=held, **edges)

    def close(self) -> None:
        """Give the terminal its settings back (also done when the object is collected)."""
        if getattr(self, "fd", None) is not None:
            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            self.fd = None

    def __del__(self):
        try:
            self.close()
        except (OSError, termios.error):
            pass
