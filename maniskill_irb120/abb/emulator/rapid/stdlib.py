"""RAPID's language built-ins (math, strings, bits, rawbytes, clocks, WaitTime, TPWrite ...) and standard data,
registered on :data:`STDLIB`. The controller's routines (MoveL, CRobT, Open, SocketReceive ...) are the emulator's
(``builtins.py``). Trigonometry works in degrees, as in RAPID; time comes from an injectable clock
(:class:`SystemClock`, :class:`ManualClock`). See docs/rapid_subset.md, "Language built-ins".
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from typing import Any

from maniskill_irb120.abb.emulator.rapid.errors import ERROR_CODES, USER_ERRNO_BASE, ProgramHalt, RapidError
from maniskill_irb120.abb.emulator.rapid.registry import Builtins
from maniskill_irb120.abb.emulator.rapid.values import RawBytes, Ref, assign_like, default_value, format_value

log = logging.getLogger(__name__)
STDLIB = Builtins()
_reg = STDLIB.register


class SystemClock:
    """Wall clock; ``scale`` < 1 makes time run faster (WaitTime 1 sleeps ``scale`` s and ClkRead agrees)."""

    def __init__(self, scale: float = 1.0):
        self.scale = scale

    def now(self) -> float:
        return time.monotonic() / self.scale

    def sleep(self, seconds: float, stop: threading.Event) -> None:
        stop.wait(seconds * self.scale)  # returns early on request_stop()


class ManualClock:
    """A clock for tests: sleeping advances ``t`` instantly and is recorded in ``sleeps``."""

    def __init__(self, t: float = 0.0):
        self.t = t
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float, stop: threading.Event) -> None:
        self.sleeps.append(seconds)
        self.t += seconds


def _argval(ok: bool, message: str) -> None:
    if not ok:
        raise RapidError("ERR_ARGVALERR", message)


def _int(v: float, what: str) -> int:
    _argval(float(v).is_integer(), f"{what} must be an integer, got {v}")
    return int(v)


# ---- math (degrees) ---------------------------------------------------------------------------------
STDLIB.add("Abs", abs)
STDLIB.add("Sin", lambda a: math.sin(math.radians(a)))
STDLIB.add("Cos", lambda a: math.cos(math.radians(a)))
STDLIB.add("Tan", lambda a: math.tan(math.radians(a)))
STDLIB.add("ATan", lambda v: math.degrees(math.atan(v)))
STDLIB.add("ATan2", lambda y, x: math.degrees(math.atan2(y, x)))
STDLIB.add("Exp", math.exp)


@_reg("Sqrt")
def _sqrt(v: float) -> float:
    _argval(v >= 0, f"Sqrt of a negative number ({v})")
    return math.sqrt(v)


@_reg("ASin")
def _asin(v: float) -> float:
    _argval(-1 <= v <= 1, f"ASin of {v}")
    return math.degrees(math.asin(v))


@_reg("ACos")
def _acos(v: float) -> float:
    _argval(-1 <= v <= 1, f"ACos of {v}")
    return math.degrees(math.acos(v))


@_reg("Pow")
def _pow(base: float, exponent: float) -> float:
    _argval(
        not (base < 0 and not exponent.is_integer()) and not (base == 0 and exponent < 0), f"Pow({base}, {exponent})"
    )
    return math.pow(base, exponent)


@_reg("Round")
def _round(val: float, Dec: float = 0) -> float:  # RAPID option names keep their case
    """Half away from zero, as the controller rounds (Python's round() is half-to-even)."""
    f = 10.0 ** _int(Dec, "Dec")
    return math.copysign(math.floor(abs(val) * f + 0.5) / f, val)


@_reg("Trunc")
def _trunc(val: float, Dec: float = 0) -> float:
    f = 10.0 ** _int(Dec, "Dec")
    return math.trunc(val * f) / f


@_reg("Dim")
def _dim(array: list, dimno: float) -> float:
    for _ in range(_int(dimno, "DimNo") - 1):
        _argval(isinstance(array, list) and array and isinstance(array[0], list), "Dim: no such dimension")
        array = array[0]
    _argval(isinstance(array, list), "Dim needs an array")
    return float(len(array))


# ---- numbers in place -----------------------------------------------------------------------------
STDLIB.add("Incr", lambda name: setattr(name, "value", name.value + 1), refs=[0])
STDLIB.add("Decr", lambda name: setattr(name, "value", name.value - 1), refs=[0])
STDLIB.add("Add", lambda name, add_value: setattr(name, "value", name.value + add_value), refs=[0])


@_reg("BookErrNo", refs=[0], with_interp=True)
def _book_errno(interp: Any, errvar: Ref) -> None:
    interp.next_errno += 1
    errvar.value = float(USER_ERRNO_BASE + interp.next_errno - 1)


# ---- strings --------------------------------------------------------------------------------------
STDLIB.add("StrLen", len)
STDLIB.add("ValToStr", format_value)


@_reg("StrPart")
def _str_part(s: str, start: float, length: float) -> str:
    i, n = _int(start, "ChPos"), _int(length, "Len")
    _argval(i >= 1 and n >= 0 and i - 1 + n <= len(s), f"StrPart({s!r}, {i}, {n}) outside the string")
    return s[i - 1 : i - 1 + n]


@_reg("NumToStr")
def _num_to_str(val: float, dec: float, Exp: bool = False) -> str:
    d = _int(dec, "Dec")
    text = f"{val:.{d}E}" if Exp else f"{math.copysign(math.floor(abs(val) * 10**d + 0.5) / 10**d, val):.{d}f}"
    return "0" + text[2:] if text.startswith("-0") and float(text) == 0 else text


@_reg("StrToVal", refs=[1])
def _str_to_val(s: str, val: Ref) -> bool:
    """Parses a num, bool, string or aggregate text into ``val``; FALSE (val unchanged) if it does not fit."""
    import ast

    text = s.strip().replace("TRUE", "True").replace("FALSE", "False")
    try:
        val.value = ast.literal_eval(text) if not isinstance(val.value, str) else s
    except (ValueError, SyntaxError, TypeError):
        return False
    return True


@_reg("ByteToStr")
def _byte_to_str(b: float, Hex: bool = False, Okt: bool = False, Bin: bool = False, Char: bool = False) -> str:
    v = _int(b, "BitData")
    _argval(0 <= v <= 255, f"byte out of range: {v}")
    return f"{v:02X}" if Hex else f"{v:03o}" if Okt else f"{v:08b}" if Bin else chr(v) if Char else str(v)


@_reg("StrToByte")
def _str_to_byte(s: str, Hex: bool = False, Okt: bool = False, Bin: bool = False, Char: bool = False) -> float:
    try:
        v = ord(s) if Char else int(s, 16 if Hex else 8 if Okt else 2 if Bin else 10)
    except (TypeError, ValueError):
        raise RapidError("ERR_ARGVALERR", f"StrToByte({s!r})") from None
    _argval(0 <= v <= 255, f"byte out of range: {v}")
    return float(v)


# ---- bits (byte operations mask to 8 bits) --------------------------------------------------------
STDLIB.add("BitAnd", lambda a, b: float(int(a) & int(b)))
STDLIB.add("BitOr", lambda a, b: float(int(a) | int(b)))
STDLIB.add("BitXOr", lambda a, b: float(int(a) ^ int(b)))
STDLIB.add("BitNeg", lambda a: float(~int(a) & 0xFF))
STDLIB.add("BitLSh", lambda a, n: float((int(a) << int(n)) & 0xFF))
STDLIB.add("BitRSh", lambda a, n: float((int(a) & 0xFF) >> int(n)))
STDLIB.add("BitCheck", lambda a, bit: bool(int(a) >> (int(bit) - 1) & 1))
STDLIB.add("BitSet", lambda ref, bit: setattr(ref, "value", float(int(ref.value) | 1 << (int(bit) - 1))), refs=[0])
STDLIB.add("BitClear", lambda ref, bit: setattr(ref, "value", float(int(ref.value) & ~(1 << (int(bit) - 1)))), refs=[0])

# ---- rawbytes -------------------------------------------------------------------------------------
INTX = {"USINT": 1, "UINT": 2, "UDINT": 4, "ULINT": 8, "SINT": -1, "INT": -2, "DINT": -4, "LINT": -8}
_INTX_FMT = {1: "B", 2: "H", 4: "I", 8: "Q", -1: "b", -2: "h", -4: "i", -8: "q"}


def _fmt(Network: bool, IntX: float | None, Float4: bool) -> str:
    if Float4:
        code = "f"
    else:
        _argval(IntX is not None and int(IntX) in _INTX_FMT, f"\\IntX must be one of {sorted(INTX)}, got {IntX}")
        code = _INTX_FMT[int(IntX)]
    return (">" if Network else "<") + code


@_reg("PackRawBytes")
def _pack(value: Any, raw: RawBytes, start: float, Network=False, IntX=None, Float4=False, ASCII=False, Hex1=False):
    """Packs ``value`` at 1-based ``start``: \\IntX/\\Float4 little-endian unless \\Network, \\ASCII text, \\Hex1."""
    if ASCII:
        chunk = value.encode("latin-1") if isinstance(value, str) else bytes([_int(value, "byte")])
    elif Hex1:
        chunk = bytes([_int(value, "Hex1 byte") & 0xFF])
    else:
        fmt = _fmt(Network, IntX, Float4)
        try:
            chunk = struct.pack(fmt, value if Float4 else _int(value, "IntX data"))
        except struct.error as e:
            raise RapidError("ERR_ARGVALERR", f"PackRawBytes {value}: {e}") from None
    raw.write(_int(start, "StartIndex"), chunk)


@_reg("UnpackRawBytes", refs=[2])
def _unpack(raw: RawBytes, start: float, value: Ref, Network=False, IntX=None, Float4=False, ASCII=None, Hex1=False):
    i = _int(start, "StartIndex")
    if ASCII is not None:
        value.value = raw.read(i, _int(ASCII, "\\ASCII count")).decode("latin-1")
    elif Hex1:
        value.value = float(raw.read(i, 1)[0])
    else:
        fmt = _fmt(Network, IntX, Float4)
        (v,) = struct.unpack(fmt, raw.read(i, struct.calcsize(fmt)))
        value.value = float(v)


@_reg("CopyRawBytes")
def _copy_raw(src: RawBytes, from_index: float, dst: RawBytes, to_index: float, NoOfBytes=None):
    i = _int(from_index, "FromIndex")
    n = len(src) - i + 1 if NoOfBytes is None else _int(NoOfBytes, "NoOfBytes")
    dst.write(_int(to_index, "ToIndex"), src.read(i, n))


STDLIB.add("RawBytesLen", lambda raw: float(len(raw)))
STDLIB.add("ClearRawBytes", lambda raw, FromIndex=1: raw.clear(int(FromIndex)))

# ---- time -----------------------------------------------------------------------------------------


@_reg("WaitTime", with_interp=True)
def _wait_time(interp: Any, time: float, InPos: bool = False) -> None:
    _argval(time >= 0, f"WaitTime {time}")
    interp.clock.sleep(time, interp.stop_event)
    interp.check_stop()


STDLIB.add(
    "ClkReset", lambda interp, c: (setattr(c, "accumulated", 0.0), setattr(c, "started_at", None)), with_interp=True
)
STDLIB.add("ClkStop", lambda interp, c: _clk_stop(c, interp.clock.now()), with_interp=True)
STDLIB.add("ClkStart", lambda interp, c: _clk_start(c, interp.clock.now()), with_interp=True)


def _clk_start(c: Any, now: float) -> None:
    if c.started_at is None:  # starting a running clock changes nothing
        c.started_at = now


def _clk_stop(c: Any, now: float) -> None:
    c.accumulated, c.started_at = c.read(now), None


@_reg("ClkRead", with_interp=True)
def _clk_read(interp: Any, c: Any, HighRes: bool = False) -> float:
    t = c.read(interp.clock.now())
    return t if HighRes else round(t, 3)


# ---- program and operator messages ----------------------------------------------------------------


@_reg("TPWrite", with_interp=True)
def _tpwrite(interp: Any, string: str, Num=None, Bool=None, Pos=None, Orient=None, Dnum=None) -> None:
    extra = next((v for v in (Num, Bool, Pos, Orient, Dnum) if v is not None), None)
    line = string + (format_value(extra) if extra is not None else "")
    interp.tp_log.append(line)
    log.info("TPWrite: %s", line)


@_reg("ErrWrite", with_interp=True)
def _errwrite(interp: Any, header: str, reason: str, RL2="", RL3="", RL4="", W=False, I=False) -> None:  # noqa: E741
    entry = " | ".join(s for s in (header, reason, RL2, RL3, RL4) if s)
    interp.err_log.append(entry)
    log.warning("ErrWrite: %s", entry)


def _stop(**_options: Any) -> None:
    raise ProgramHalt("stop")


STDLIB.add("Stop", _stop)
STDLIB.add("TPErase", lambda: None)


def _speed(v: float) -> list[float]:
    return [v, 500.0, 5000.0, 1000.0]


def _zone(tcp: float, ori: float, eout: float, zori: float, leax: float, reax: float) -> list[Any]:
    return [False, tcp, ori, eout, zori, leax, reax]


_POSE0 = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]
_LOAD0 = [0.001, [0.0, 0.0, 0.001], [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0]
_SPEEDS = [5, 10, 20, 30, 40, 50, 60, 80, 100, 150, 200, 300, 400, 500, 600, 800, 1000, 1500, 2000, 2500, 3000]
_ZONES = {0: (0.3, 0.3, 0.3, 0.03, 0.3, 0.03), 1: (1, 1, 1, 0.1, 1, 0.1)} | {
    z: (z, 1.5 * z, 1.5 * z, 0.15 * z, 1.5 * z, 0.15 * z) for z in (10, 15, 20, 30, 40, 50, 60, 80, 100, 150, 200)
}
_ZONES.update({5: (5, 8, 8, 0.8, 8, 0.8), 15: (15, 23, 23, 2.3, 23, 2.3), 150: (150, 225, 225, 23, 225, 23)})


# OpMode()'s symnum values (ABB, RAPID Instructions, Functions and Data types: OpMode, symnum)
OP_MODES = {"OP_UNDEF": 0, "OP_AUTO": 1, "OP_MAN_PROG": 2, "OP_MAN_TEST": 3}


def system_data() -> dict[str, Any]:
    """Predefined data (lower-case names): speeds v5..v7000, vmax, zones fine/z0..z200, tool0, wobj0, load0,
    pi, the ERR_* codes, the OP_* operating modes and the \\IntX constants (USINT ... LINT)."""
    data: dict[str, Any] = {f"v{v}": assign_like(default_value("speeddata"), _speed(v)) for v in _SPEEDS}
    data.update({f"v{v}": assign_like(default_value("speeddata"), _speed(v)) for v in (4000, 5000, 6000, 7000)})
    data["vmax"] = assign_like(default_value("speeddata"), _speed(7000))
    data["fine"] = assign_like(default_value("zonedata"), [True, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    for z, vals in _ZONES.items():
        data[f"z{z}"] = assign_like(default_value("zonedata"), _zone(*map(float, vals)))
    data["load0"] = assign_like(default_value("loaddata"), _LOAD0)
    data["tool0"] = assign_like(default_value("tooldata"), [True, _POSE0, _LOAD0])
    data["wobj0"] = assign_like(default_value("wobjdata"), [False, True, "", _POSE0, _POSE0])
    data["pi"] = math.pi
    data["wait_max"] = 8388608.0  # ABB's "wait forever" \Time value
    data.update({k.lower(): float(v) for k, v in OP_MODES.items()})
    data.update({k.lower(): float(v) for k, v in ERROR_CODES.items()})
    data.update({k.lower(): float(v) for k, v in INTX.items()})
    return data
