"""Device drivers on event streams: the keyboard through a real pseudo-terminal (bytes as a terminal sends them,
a fake clock for hold-to-run), the SpaceMouse on synthetic HID reports, the gamepad on joystick events written
to a FIFO the driver opens as it opens /dev/input/js0."""

from __future__ import annotations

import os
import pty
import struct
import termios

import pytest

from maniskill_irb120.teleop.devices import Command, Merged, Scripted, merge, open_device
from maniskill_irb120.teleop.gamepad import EVENT, JS_AXIS, JS_BUTTON, JS_INIT, Gamepad, GamepadMap, JoystickEvents
from maniskill_irb120.teleop.keyboard import Keyboard, parse_keys
from maniskill_irb120.teleop.spacemouse import SpaceMouse, SpaceMouseReports, find_spacemouse


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# ---------------------------------------------------------------- keyboard
def test_terminal_bytes_parse_to_keys():
    assert parse_keys(b"wA \r\x7f") == ["w", "a", " ", "\r", "\x7f"]
    assert parse_keys(b"\x1b[A\x1b[D\x1bOB") == ["up", "left", "down"]  # arrows, both cursor-key modes
    assert parse_keys(b"\x1b[15~q") == ["q"]  # F5 skipped
    assert parse_keys(b"\x1b") == ["esc"]


@pytest.fixture
def terminal():
    master, slave = pty.openpty()
    before = termios.tcgetattr(slave)
    clock = FakeClock()
    kb = Keyboard(fd=slave, hold_s=0.1, clock=clock)
    yield kb, master, clock, before
    kb.close()
    os.close(master)
    os.close(slave)


def test_keyboard_moves_while_events_are_fresh_and_stops_after_hold(terminal):
    kb, master, clock, _ = terminal
    assert kb.poll() == Command()
    os.write(master, b"w")
    c = kb.poll()
    assert c.translation == (1.0, 0.0, 0.0) and c.deadman
    clock.t += 0.06  # no new event, still within hold_s: the motion goes on (between autorepeats)
    assert kb.poll().translation == (1.0, 0.0, 0.0)
    os.write(master, b"w")  # an autorepeat event
    clock.t += 0.02
    assert kb.poll().deadman
    clock.t += 0.11  # a period with no event fresher than hold_s: stop
    c = kb.poll()
    assert not c.moving and not c.deadman
    os.write(master, b"\x1b[Dx")  # left arrow and yaw- in one read
    c = kb.poll()
    assert c.translation == (0.0, 1.0, 0.0) and c.yaw == -1.0


def test_keyboard_edges_are_reported_once(terminal):
    kb, master, _, _ = terminal
    os.write(master, b" \rn\x7fq")
    c = kb.poll()
    assert (c.gripper_toggle, c.save, c.discard, c.reset, c.quit) == (True,) * 5 and not c.moving
    assert kb.poll() == Command()


def test_keyboard_gives_the_terminal_back_and_refuses_a_pipe(terminal):
    kb, _, _, before = terminal
    assert termios.tcgetattr(kb.fd)[3] & termios.ICANON == 0  # cbreak while in use
    fd = kb.fd
    kb.close()
    assert termios.tcgetattr(fd) == before
    with pytest.raises(RuntimeError, match="closed"):
        kb.poll()
    r, w = os.pipe()
    try:
        with pytest.raises(ValueError, match="not one"):
            Keyboard(fd=r)
    finally:
        os.close(r), os.close(w)


# ---------------------------------------------------------------- SpaceMouse
def report(rid: int, *values: int) -> bytes:
    return bytes([rid]) + struct.pack(f"<{len(values)}h", *values)


def buttons(mask: int) -> bytes:
    return bytes([3, mask & 0xFF, mask >> 8])


def test_spacemouse_reports_old_and_new_formats():
    sm = SpaceMouseReports(full_scale=350, dead_zone=0.1)
    sm.feed(report(1, 0, -350, 0))  # pushed away from the operator (device y toward the operator)
    assert sm.command().translation == (1.0, 0.0, 0.0)
    sm.feed(report(1, -350, 0, -350))  # left and lifted
    assert sm.command().translation == (0.0, 1.0, 1.0)
    sm.feed(report(1, 0, 0, 0))
    sm.feed(report(2, 0, 0, -175))  # old format: rotation in report 2, twisted counter-clockwise
    c = sm.command()
    assert c.translation == (0.0, 0.0, 0.0) and c.yaw == pytest.approx((0.5 - 0.1) / 0.9) and c.deadman
    sm.feed(report(1, 20, 20, 20, 0, 0, 0))  # new format: both in report 1; small values inside the dead zone
    c = sm.command()
    assert not c.moving and not c.deadman  # the puck let go: a real release
    sm.feed(report(1, 0, 0, 1000, 0, 0, 0))  # beyond full scale: clipped
    assert sm.command().translation == (0.0, 0.0, -1.0)


def test_spacemouse_buttons_are_edges():
    sm = SpaceMouseReports(buttons=("gripper_toggle", "save"))
    sm.feed(buttons(0b01))
    assert sm.command().gripper_toggle
    sm.feed(buttons(0b01))  # still held: no new press
    assert not sm.command().gripper_toggle
    sm.feed(buttons(0b10))
    c = sm.command()
    assert c.save and not c.gripper_toggle
    with pytest.raises(ValueError, match="fly"):
        SpaceMouseReports(buttons=("fly",))


class FakeHid:
    """hidapi's device and module, as far as the driver uses them."""

    def __init__(self, reports=(), devices=()):
        self.reports, self.devices, self.closed = list(reports), list(devices), False

    def read(self, size):
        return list(self.reports.pop(0)) if self.reports else []

    def close(self):
        self.closed = True

    def enumerate(self):
        return self.devices


def test_spacemouse_device_drains_pending_reports_and_finds_the_device():
    dev = FakeHid([report(1, 0, -350, 0), report(1, 0, -175, 0), buttons(1)])
    sm = SpaceMouse(device=dev)
    c = sm.poll()
    assert c.translation[0] == pytest.approx((0.5 - 0.1) / 0.9) and c.gripper_toggle  # the latest report wins
    assert sm.poll().translation[0] == pytest.approx((0.5 - 0.1) / 0.9)  # no report: the state holds
    sm.close()
    assert dev.closed
    mouse = dict(vendor_id=0x256F, product_id=0xC635, path=b"/dev/hidraw3")
    assert find_spacemouse(FakeHid(devices=[dict(vendor_id=1, product_id=2, path=b"x"), mouse])) is mouse
    with pytest.raises(RuntimeError, match="no 3Dconnexion SpaceMouse"):
        find_spacemouse(FakeHid(devices=[dict(vendor_id=1, product_id=2, path=b"x")]))


# ---------------------------------------------------------------- gamepad
def js(value: int, kind: int, number: int, t: int = 0) -> bytes:
    return EVENT.pack(t, value, kind, number)


def test_joystick_events_map_sticks_buttons_and_deadman():
    ev = JoystickEvents(GamepadMap())
    stream = js(0, JS_BUTTON | JS_INIT, 0) + js(1, JS_BUTTON | JS_INIT, 5) + js(-32767, JS_AXIS, 1)
    ev.feed(stream[:5])  # events split anywhere
    ev.feed(stream[5:])
    c = ev.command()
    assert c.translation == (1.0, 0.0, 0.0) and c.deadman and not c.gripper_toggle  # RB down when opened
    ev.feed(js(0, JS_BUTTON, 5) + js(1, JS_BUTTON, 0) + js(16384, JS_AXIS, 3) + js(3000, JS_AXIS, 4))
    c = ev.command()
    assert not c.deadman and c.gripper_toggle  # RB released: a real release
    assert c.yaw == pytest.approx(-((16384 / 32767) - 0.15) / 0.85) and c.translation[2] == 0.0  # 4: dead zone
    ev.feed(js(1, JS_BUTTON, 7) + js(1, JS_BUTTON, 6))
    c = ev.command()
    assert c.save and c.discard and not ev.command().save


def test_gamepad_reads_a_joystick_node(tmp_path):
    path = tmp_path / "js0"
    os.mkfifo(path)
    pad = Gamepad(str(path), layout="dualsense")
    w = os.open(path, os.O_WRONLY)
    try:
        assert pad.poll() == Command()
        os.write(w, js(1, JS_BUTTON, 5) + js(32767, JS_AXIS, 0) + js(1, JS_BUTTON, 9))
        c = pad.poll()
        assert c.translation == (0.0, -1.0, 0.0) and c.deadman and c.save  # right; R1 held; options saves
    finally:
        os.close(w)
        pad.close()
    with pytest.raises(RuntimeError, match="cannot open the gamepad"):
        Gamepad(str(tmp_path / "js9"))
    with pytest.raises(ValueError, match="layout"):
        Gamepad(str(path), layout="n64")
    with pytest.raises(ValueError, match="fly"):
        GamepadMap(buttons={0: "fly"})


# ---------------------------------------------------------------- the interface
def test_merge_takes_motion_from_the_mover_and_edges_from_both():
    mouse = Command(translation=(0.5, 0.0, 0.0), deadman=True)
    keys = Command(save=True)
    m = merge(mouse, keys)
    assert m.translation == (0.5, 0.0, 0.0) and m.deadman and m.save
    both = Merged(Scripted([Command()]), Scripted([Command(yaw=1.0, deadman=True, quit=True)]))
    c = both.poll()
    assert c.yaw == 1.0 and c.deadman and c.quit
    assert both.poll().quit  # the scripts ran out: quit


def test_bad_commands_and_devices_are_named():
    with pytest.raises(ValueError, match="in \\[-1, 1\\]"):
        Command(translation=(2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="unknown device 'wiimote'"):
        open_device("wiimote")


def test_the_teleop_command_names_a_bad_device(capsys, monkeypatch):
    from maniskill_irb120.cli import main

    assert main(["teleop", "--device", "wiimote"]) == 2
    assert "--device wiimote: unknown device 'wiimote'" in capsys.readouterr().err
    r, w = os.pipe()
    monkeypatch.setattr("sys.stdin", os.fdopen(r))
    try:
        assert main(["teleop", "--device", "keyboard"]) == 2
        assert "standard input is not one" in capsys.readouterr().err
    finally:
        os.close(w)
