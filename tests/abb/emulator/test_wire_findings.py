"""The issue's findings on the emulator's wire (``maniskill-irb120 emulator --listen tcp://127.0.0.1:0``), against
the emulator running the shipped RAPID files (core, socket channel, world zone) over TCP, byte by byte as a PC
sends them; and what already worked keeps working (noise, slow frames, wrong payload lengths)."""

from __future__ import annotations

import socket
import time
from urllib.parse import urlparse

import numpy as np
import pytest

pytest.importorskip("lark")

from maniskill_irb120.abb.emulator.controller import ControllerEmulator  # noqa: E402
from maniskill_irb120.abb.protocol import (  # noqa: E402
    ErrorCode,
    Frame,
    FrameParser,
    GetState,
    MsgType,
    RobotState,
    Status,
    Stop,
    ToolStep,
    command_frame,
    decode_reply,
)


class Wire:
    """A raw TCP client: frames out, frames in, nothing retried."""

    def __init__(self, url: str):
        u = urlparse(url)
        self.sock = socket.create_connection((u.hostname, u.port), timeout=2.0)
        self.parser = FrameParser()
        self.frames: list[Frame] = []

    def send(self, raw: bytes) -> None:
        self.sock.sendall(raw)

    def reply(self, timeout: float = 1.0) -> Frame | None:
        """The next frame from the controller, or None if none came within ``timeout``."""
        end = time.monotonic() + timeout
        while not self.frames:
            left = end - time.monotonic()
            if left <= 0:
                return None
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(256)
            except TimeoutError:
                return None
            if not data:
                raise EOFError("the controller closed the connection")
            self.frames += self.parser.feed(data)
        return self.frames.pop(0)

    def ask(self, msg, seq: int, timeout: float = 1.0, resend_s: float = 0.25) -> Frame:
        """The reply to ``msg``, resending the identical frame every ``resend_s`` as the client does (a server that
        turns to this connection drops what it sent before); replies to other frames are skipped."""
        raw = command_frame(msg, seq).encode()
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            self.send(raw)
            until = time.monotonic() + min(resend_s, left)
            while (frame := self.reply(until - time.monotonic())) is not None:
                if frame.seq == seq and frame.type == MsgType.REPLY | msg.TYPE:
                    return frame
        raise AssertionError(f"no reply to {msg} (seq {seq})")

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def emu():
    emu = ControllerEmulator("tcp")
    emu.url = emu.start()
    yield emu
    emu.stop()
    assert emu.error is None, emu.error


def test_a_reply_frame_is_dropped_and_the_server_keeps_serving(emu):
    """Finding 1: one frame with a valid CRC and type 0x85 (what a serial line echoing the controller's own replies
    sends) stopped the RAPID program (``tx{3} := 128 + kind`` overflowed a byte) and no client could connect
    again. A reply type (bit 0x80) is now dropped without a reply; unknown command types are still refused."""
    wire = Wire(emu.url)
    wire.send(Frame(0x85, 7, bytes(26)).encode())  # an echoed STOP reply
    wire.send(Frame(0xFF, 8).encode())
    assert wire.reply(0.3) is None
    frame = wire.ask(GetState(), 9)
    assert frame.type == MsgType.REPLY | MsgType.STATE and frame.seq == 9
    wire.send(Frame(0x7F, 10).encode())
    frame = wire.reply()
    assert frame.type == 0xFF and RobotState.parse(frame.payload).error == ErrorCode.UNKNOWN_TYPE
    wire.close()
    again = Wire(emu.url)  # the program still runs: a new client is served
    assert again.ask(GetState(), 1).type == MsgType.REPLY | MsgType.STATE
    again.close()
    assert emu.error is None


def test_a_new_connection_reusing_a_sequence_number_is_executed(emu):
    """Finding 2: after a STATE with seq 42 on one connection, a STOP with seq 42 on the next was answered with the
    stale 0x81 reply and not executed (``lastSeq`` was never reset; duplicates were matched on the sequence number
    alone). The cache is now cleared when a connection opens and matched on sequence number, type and CRC."""
    a = Wire(emu.url)
    assert a.ask(GetState(), 42).type == MsgType.REPLY | MsgType.STATE
    a.close()
    b = Wire(emu.url)
    frame = b.ask(Stop(), 42)
    assert frame.type == MsgType.REPLY | MsgType.STOP and frame.seq == 42
    assert decode_reply(frame).status == Status.HELD
    # and a motion command reusing the number runs: the robot moves once
    b.close()
    c = Wire(emu.url)
    frame = c.ask(ToolStep(0.005, 0.0, 0.0, 0.0), 42)
    assert frame.type == MsgType.REPLY | MsgType.TOOL_STEP and decode_reply(frame).error == ErrorCode.OK
    assert emu.moves == 1
    c.close()


def test_a_repeated_frame_on_one_connection_is_answered_from_the_cache(emu):
    """Finding 2's other half: the same frame again (same number, type and CRC: a PC's retry) is answered with the
    cached reply and not executed again; the same number with another type or payload is a new command."""
    wire = Wire(emu.url)
    raw = command_frame(ToolStep(0.005, 0.0, 0.0, 0.0), 77).encode()
    replies = []
    for _ in range(3):
        wire.send(raw)
        replies.append(wire.reply())
    assert all(r == replies[0] for r in replies) and replies[0].type == MsgType.REPLY | MsgType.TOOL_STEP
    assert emu.moves == 1
    assert wire.ask(GetState(), 77).type == MsgType.REPLY | MsgType.STATE  # same number, other type: answered anew
    frame = wire.ask(ToolStep(0.004, 0.0, 0.0, 0.0), 77)  # and other payload (CRC): executed
    assert decode_reply(frame).error == ErrorCode.OK and emu.moves == 2
    wire.close()


def test_a_silent_open_connection_does_not_lock_out_a_new_client(emu):
    """Finding 3: while one connection stayed open and silent (a PC that crashed without closing), a new client was
    never served. Once the current client has been silent for SILENCE_S (two heartbeats) and a new one is waiting,
    the old connection is closed, the robot held, and the new client served."""
    old = Wire(emu.url)
    assert old.ask(GetState(), 1).type == MsgType.REPLY | MsgType.STATE  # then silence, connection left open
    new = Wire(emu.url)
    t0 = time.monotonic()
    frame = new.ask(GetState(), 1, timeout=3.0)  # the same number as the old client's: not the old reply's cache
    assert time.monotonic() - t0 < 2.0
    assert frame.type == MsgType.REPLY | MsgType.STATE and decode_reply(frame).status == Status.HELD
    with pytest.raises(EOFError):  # the old one was closed
        old.reply(1.0)
    assert decode_reply(new.ask(ToolStep(0.005, 0.0, 0.0, 0.0), 2)).error == ErrorCode.OK
    old.close()
    new.close()


def test_a_busy_client_is_not_replaced(emu):
    """The silence rule only replaces a silent client: one sending STATE every 0.2 s keeps the line while another
    connection waits. What the waiting client sent meanwhile is dropped when the server turns to it; it is served
    once it sends again."""
    busy = Wire(emu.url)
    waiting = Wire(emu.url)
    waiting.send(command_frame(GetState(), 1).encode())
    for seq in range(10):
        assert busy.ask(GetState(), seq).seq == seq
        time.sleep(0.2)
    assert waiting.reply(0.1) is None
    busy.close()
    assert waiting.reply(0.5) is None  # its frame from before it was served: dropped, never answered
    assert waiting.ask(GetState(), 2, timeout=2.0).type == MsgType.REPLY | MsgType.STATE  # served once free
    waiting.close()


# --------------------------------------------------------------------------- what already worked
def test_a_noise_flood_then_a_frame_is_answered(emu):
    """20 kB of noise (no sync byte in it: a sync's length and body would swallow the frame after it) is skipped
    and the next frame is answered; nothing in the noise stops the program."""
    noise = np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8)
    noise = bytes(noise[noise != 0xA5])
    wire = Wire(emu.url)
    wire.send(noise)
    frame = wire.ask(GetState(), 5, timeout=30.0)
    assert frame.type == MsgType.REPLY | MsgType.STATE and frame.seq == 5
    wire.close()


def test_a_frame_fed_byte_by_byte_is_answered(emu):
    """A frame whose bytes come 20 ms apart (a slow or bursty line: 9600 baud needs 1 ms) is still one frame: its
    rest may take FRAME_S (0.5 s) from its sync."""
    wire = Wire(emu.url)
    for b in command_frame(ToolStep(0.005, 0.0, 0.0, 0.0), 3).encode():
        wire.send(bytes([b]))
        time.sleep(0.02)
    frame = wire.reply()
    assert frame.type == MsgType.REPLY | MsgType.TOOL_STEP and decode_reply(frame).error == ErrorCode.OK
    wire.close()


@pytest.mark.parametrize("payload", [b"", bytes(8), bytes(10), bytes(32)])
def test_a_wrong_payload_length_is_refused(emu, payload):
    wire = Wire(emu.url)
    wire.send(Frame(MsgType.TOOL_STEP, 4, payload).encode())
    frame = wire.reply()
    assert frame.type == MsgType.REPLY | MsgType.TOOL_STEP and decode_reply(frame).error == ErrorCode.BAD_LENGTH
    assert emu.moves == 0
    wire.close()
