"""The controller's end of the link (a pty master or an accepted TCP connection), with the line speed,
latency and reply faults the emulator injects (``--fault``). See docs/emulator.md.
"""

from __future__ import annotations

import os
import re
import select
import socket
import time
from collections import deque
from collections.abc import Callable

FAULTS = ("drop", "corrupt", "dup", "delay", "disconnect", "motors_off", "estop")


def parse_faults(spec: str | None) -> dict[int, tuple[str, float]]:
    """``"drop@2,corrupt@3,dup@4,delay@5:300,disconnect@6,motors_off@7,estop@8"``: what happens to the N-th reply
    the controller sends (1-based). delay takes milliseconds; estop (an emergency stop) and motors_off (a guard
    stop, or the enabling device let go) happen as that reply goes out: the program halts and answers nothing
    more until the operator restarts it."""
    faults: dict[int, tuple[str, float]] = {}
    for item in filter(None, (spec or "").split(",")):
        m = re.fullmatch(r"(\w+)@(\d+)(?::(\d+(?:\.\d+)?))?", item.strip())
        if not m or m.group(1) not in FAULTS:
            raise ValueError(f"fault {item!r}: use KIND@N[:MS] with KIND one of {FAULTS}, e.g. delay@3:300")
        faults[int(m.group(2))] = (m.group(1), float(m.group(3) or 0))
    return faults


class Channel:
    """The controller's end of the link: a pty master (serial) or an accepted TCP connection; injects
    ``faults`` into the replies it sends (see :func:`parse_faults`). With ``baud`` a serial line's speed is
    emulated (a pty has none): 10 bit times per byte (8N1), each way, one byte after the other. ``latency_s``
    holds every incoming byte back that long (a slow network, a busy controller: the command latency sysid fits)."""

    def __init__(
        self,
        faults: dict[int, tuple[str, float]],
        on_fault: Callable[[str], None],
        baud: int | None = None,
        latency_s: float = 0.0,
    ):
        self.fd: int | None = None
        self.conn: socket.socket | None = None
        self.buf: deque[tuple[int, float]] = deque()  # (byte, when its stop bit has arrived)
        self.faults, self.on_fault, self.replies = faults, on_fault, 0
        self.byte_s, self.latency_s = (10.0 / baud if baud else 0.0), latency_s
        self._rx_free = 0.0  # when the receive line is free for the next byte

    def read_byte(self, timeout: float) -> int | None:
        if not self.buf:
            src = self.fd if self.conn is None else self.conn
            if src is None or not select.select([src], [], [], max(0.0, timeout))[0]:
                return None
            data = os.read(self.fd, 256) if self.conn is None else self.conn.recv(256)
            if not data:
                raise EOFError("peer closed")
            now = time.monotonic()
            for b in data:
                self._rx_free = max(now + self.latency_s, self._rx_free) + self.byte_s
                self.buf.append((b, self._rx_free))
        b, arrives = self.buf.popleft()
        if (wait := arrives - time.monotonic()) > 0:
            time.sleep(wait)
        return b

    def read_ready(self, limit: int) -> bytes:
        """Up to ``limit`` bytes that have already arrived, without waiting (a read that takes what is there)."""
        out = bytearray()
        while len(out) < limit:
            if not self.buf or self.buf[0][1] > time.monotonic():
                src = self.fd if self.conn is None else self.conn
                if self.buf or src is None or not select.select([src], [], [], 0)[0]:
                    break
            try:
                b = self.read_byte(0.0)
            except EOFError:  # the peer closed after these bytes: they are read now, the close on the next read
                break
            if b is None:
                break
            out.append(b)
        return bytes(out)

    def clear(self) -> None:
        """The bytes taken from the line and not yet read are dropped (the link turns to another connection)."""
        self.buf.clear()

    def discard_input(self) -> None:
        """ClearIOBuff: every byte received and not yet read is dropped, those the emulator has taken from the line
        and those still waiting in the device (the pty's input). ABB's ClearIOBuff clears the input buffer of a
        serial channel (docs/rapid_subset.md, "Controller behaviour the emulator models"): a byte the PC sent
        before it is never read after it."""
        self.buf.clear()
        src = self.fd if self.conn is None else self.conn
        while src is not None and select.select([src], [], [], 0)[0]:
            try:
                data = os.read(self.fd, 4096) if self.conn is None else self.conn.recv(4096)
            except OSError:  # the other end is gone (a pty's slave closed: EIO)
                break
            if not data:
                break
        self._rx_free = 0.0

    def write(self, data: bytes) -> None:
        self.replies += 1
        kind, arg = self.faults.get(self.replies, (None, 0.0))
        if kind == "drop":
            return
        if kind == "corrupt":
            data = data[:8] + bytes([data[8] ^ 0x5A]) + data[9:]
        elif kind == "dup":
            data = data + data
        elif kind == "delay":
            time.sleep(arg / 1000)
        elif kind in ("motors_off", "estop"):
            self.on_fault(kind)  # the controller halts the program: this reply still goes out, nothing after it
        elif kind == "disconnect":  # half a frame, then the line goes dead
            self._send(data[: len(data) // 2])
            if self.conn is not None:
                self.conn.shutdown(socket.SHUT_RDWR)
            return
        self._send(data)

    def _send(self, data: bytes) -> None:
        time.sleep(len(data) * self.byte_s)  # the peer has the frame once its last byte is through
        if self.conn is None:
            os.write(self.fd, data)
        else:
            self.conn.sendall(data)
