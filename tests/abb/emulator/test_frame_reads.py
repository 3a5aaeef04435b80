"""Whole-frame reads: the server takes what has come on the channel in one call (not one call per byte), through
base RAPID on the serial side (ReadRawBytes on an ``Open ...\\Bin`` device, RawBytesLen, UnpackRawBytes) and
SocketReceive ``\\RawData`` on TCP, and keeps every byte it has not consumed (the channel module keeps what did
not fit); and the emulator's ReadRawBytes as the server relies on it."""

from __future__ import annotations

import os
import tty

import pytest

pytest.importorskip("lark")

from maniskill_irb120.abb.client import ABBRobot  # noqa: E402
from maniskill_irb120.abb.emulator.controller import ControllerEmulator  # noqa: E402
from maniskill_irb120.abb.emulator.rapid import RapidRuntimeError  # noqa: E402

READS = {"serial": ("ReadRawBytes", "ReadBin"), "tcp": ("SocketReceive",)}


def counted(fn, calls: list):
    """``fn``, recording each call in ``calls``."""

    def wrapped(*a, **k):
        calls.append(fn)
        return fn(*a, **k)

    return wrapped


@pytest.mark.parametrize("channel", ["serial", "tcp"])
def test_a_frame_is_read_in_one_channel_call(channel):
    """One call per byte cost a channel call and its statements per byte (a STATE frame is 6 bytes, a tool step 15):
    a frame that comes at once is taken in one call."""
    emu = ControllerEmulator(channel, statement_cost_us=0.0)
    calls = []
    for name in READS[channel]:
        b = emu.interp.builtins.get(name)
        b.fn = counted(b.fn, calls)
    with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
        robot.state()
        n0, s0 = len(calls), emu.interp.statements
        robot.state()
        robot.move_tool([0.2, 0, 0, 0, 1.0])
        assert len(calls) - n0 <= 2 * 1 + 1  # two frames (and the read waiting for the next one)
        assert emu.interp.statements - s0 < 800  # the per-byte reads took ~1,000 for these two
    emu.stop()
    assert emu.error is None, emu.error


PROBE = """MODULE Probe
    VAR byte buf{8};
    VAR rawbytes raw;
    VAR iodev shut;
    PROC IRB120Server()
    ENDPROC
    FUNC num ReadShut()
        ReadRawBytes shut, raw\\NoOfBytes:=1\\Time:=0.1;
        RETURN 0;
    ENDFUNC
    FUNC num ReadCount(num n)
        VAR iodev dev;
        Open "COM1:", dev\\Bin;
        ReadRawBytes dev, raw\\NoOfBytes:=n\\Time:=0.1;
        RETURN n;
    ERROR
        IF ERRNO = ERR_DEV_MAXTIME RETURN -1;
        RAISE;
    ENDFUNC
ENDMODULE
"""


@pytest.fixture
def probe(tmp_path):
    """The serial channel module beside a probe module, its device a pty the test writes the PC's bytes into."""
    rapid = tmp_path / "probe.mod"
    rapid.write_text(PROBE)
    emu = ControllerEmulator("serial", rapid, statement_cost_us=0.0)
    emu.link.fd, pc = os.openpty()
    tty.setraw(pc)
    emu.interp.call("IRB120ChanOpen")
    yield emu, pc
    os.close(pc)
    os.close(emu.link.fd)


def read(emu, first: int, room: int, timeout: float) -> tuple[float, list[int]]:
    got = emu.interp.call("IRB120ChanRead", emu.interp.ref("buf"), first, room, timeout)
    return got, [int(b) for b in emu.interp.get("buf")]


def test_the_channel_hands_over_what_came_at_an_offset_and_keeps_the_rest(probe):
    """IRB120ChanRead takes what has come (ReadRawBytes without \\NoOfBytes), at most ``room`` bytes into the
    server's buffer from ``first``; what did not fit is handed over by the next call, before the device is read
    again: no byte is lost, so the server can rescan the bytes after a corrupted frame."""
    emu, pc = probe
    os.write(pc, bytes([0xA5, 1, 2, 3, 4]))
    assert read(emu, 1, 1, 0.5) == (1, [0xA5, 0, 0, 0, 0, 0, 0, 0])
    assert read(emu, 3, 3, 0.5) == (3, [0xA5, 0, 1, 2, 3, 0, 0, 0])
    assert read(emu, 6, 3, 0.5) == (1, [0xA5, 0, 1, 2, 3, 4, 0, 0])
    assert read(emu, 1, 8, 0.1)[0] == -1  # nothing more came: ERR_DEV_MAXTIME, -1


def test_readrawbytes_with_a_count_times_out_when_not_all_came(probe):
    """\\Time expiring before \\NoOfBytes came raises ERR_DEV_MAXTIME; the bytes that did come are consumed (the
    emulator's conservative reading of an undocumented case, verify). The server therefore never reads with a
    count: it takes what has come and keeps it."""
    emu, pc = probe
    os.write(pc, bytes([7, 8]))
    assert emu.interp.call("ReadCount", 4) == -1
    os.write(pc, bytes([9]))
    assert read(emu, 1, 1, 0.5) == (1, [9, 0, 0, 0, 0, 0, 0, 0])


def test_readrawbytes_refuses_more_than_a_rawbytes_holds_and_a_closed_device(probe):
    emu, _ = probe
    with pytest.raises(RapidRuntimeError, match=r"1025 bytes asked, 1\.\.1024 can be read at once"):
        emu.interp.call("ReadCount", 1025)
    with pytest.raises(RapidRuntimeError, match="the device is not open"):
        emu.interp.call("ReadShut")
