"""RAPID data in Python: how each data type is represented, its default value, and assignment rules. Value
types have value semantics (:func:`assign_like` copies into the shape of the existing value, so ``p2 := p1`` never
aliases); non-value types (``rawbytes``, ``clock``, devices, unknown types) are objects with identity, handed over
as themselves. A ``num`` is a 32-bit float (:func:`num32`). See docs/rapid_subset.md, "Data types".
"""

from __future__ import annotations

import struct
from typing import Any

from maniskill_irb120.abb.emulator.rapid.errors import RapidError

NUMERIC_TYPES = {"num", "dnum", "byte", "errnum", "intnum"}
_N = "num"
# record type -> [(field, type, default or None for the type's default)], in declaration order
RECORD_TYPES: dict[str, list[tuple[str, str, Any]]] = {
    "pos": [("x", _N, None), ("y", _N, None), ("z", _N, None)],
    "orient": [("q1", _N, 1.0), ("q2", _N, None), ("q3", _N, None), ("q4", _N, None)],
    "pose": [("trans", "pos", None), ("rot", "orient", None)],
    "confdata": [("cf1", _N, None), ("cf4", _N, None), ("cf6", _N, None), ("cfx", _N, None)],
    "extjoint": [(f"eax_{c}", _N, 9e9) for c in "abcdef"],
    "robjoint": [(f"rax_{i}", _N, None) for i in range(1, 7)],
    "robtarget": [("trans", "pos", None), ("rot", "orient", None), ("robconf", "confdata", None)]
    + [("extax", "extjoint", None)],
    "jointtarget": [("robax", "robjoint", None), ("extax", "extjoint", None)],
    "speeddata": [("v_tcp", _N, None), ("v_ori", _N, None), ("v_leax", _N, None), ("v_reax", _N, None)],
    "zonedata": [("finep", "bool", None)]
    + [(f, _N, None) for f in ("pzone_tcp", "pzone_ori", "pzone_eout", "zone_ori", "zone_leax", "zone_reax")],
    "loaddata": [("mass", _N, None), ("cog", "pos", None), ("aom", "orient", None)]
    + [("ix", _N, None), ("iy", _N, None), ("iz", _N, None)],
    "tooldata": [("robhold", "bool", None), ("tframe", "pose", None), ("tload", "loaddata", None)],
    "wobjdata": [("robhold", "bool", None), ("ufprog", "bool", None), ("ufmec", "string", None)]
    + [("uframe", "pose", None), ("oframe", "pose", None)],
}


_PREDEFINED = frozenset(RECORD_TYPES)
_F32 = struct.Struct("<f")


def num32(v: float) -> float:
    """``v`` as the IRC5 holds a ``num``: the nearest 32-bit float (16777216 + 1 is 16777216; 0.1 is
    0.100000001490116). Beyond float32's range (about 3.4E38) a TypeError: a value error that stops the program."""
    try:
        return _F32.unpack(_F32.pack(v))[0]
    except OverflowError:
        raise TypeError(f"{v} is outside the range of a num (a 32-bit float, about 3.4E38)") from None


def is_num32_range(v: float) -> bool:
    """Whether ``v`` is within float32's range (a ``num`` can hold it, rounded)."""
    return abs(v) <= 3.4028234663852886e38


def is_num32(v: float) -> bool:
    """Whether ``v`` is exactly a float32 (a ``num`` can hold it)."""
    try:
        return _F32.unpack(_F32.pack(v))[0] == v
    except OverflowError:
        return False


def define_record(name: str, fields: list[tuple[str, str]]) -> None:
    """Register a record type (a RAPID ``RECORD`` declaration, or one an emulator wants to expose).

    The table is process-wide (as RAPID's installed types are controller-wide); predefined types stay as they are.
    """
    if name.lower() in _PREDEFINED:
        raise ValueError(f"{name} is a predefined type")
    RECORD_TYPES[name.lower()] = [(f.lower(), t.lower(), None) for f, t in fields]
    _HAS_BYTE.clear()


class Record:
    """A RAPID record value: ``rec.trans.x``, ``rec["trans"]``, ``rec[0]``; ``to_python()`` gives plain dicts."""

    __slots__ = ("type", "_fields")

    def __init__(self, type_name: str, fields: dict[str, Any]):
        object.__setattr__(self, "type", type_name)
        object.__setattr__(self, "_fields", fields)

    def __getattr__(self, name: str) -> Any:
        try:
            return self._fields[name.lower()]
        except KeyError:
            raise AttributeError(f"{self.type} has no component {name!r}") from None

    def __setattr__(self, name: str, value: Any) -> None:
        self[name] = value

    def __getitem__(self, key: str | int) -> Any:
        return self._fields[self.key(key)]

    def __setitem__(self, key: str | int, value: Any) -> None:
        key = self.key(key)
        self._fields[key] = assign_like(self._fields[key], value)

    def key(self, key: str | int) -> str:
        """The field name for a name (any case) or a 0-based position."""
        if isinstance(key, int):
            return list(self._fields)[key]
        if key.lower() not in self._fields:
            raise KeyError(f"{self.type} has no component {key!r}")
        return key.lower()

    def fields(self) -> list[str]:
        return list(self._fields)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Record) and self.type == other.type and self._fields == other._fields

    def copy(self) -> Record:
        return Record(self.type, {k: copy_value(v) for k, v in self._fields.items()})

    def to_python(self) -> dict[str, Any]:
        return {k: v.to_python() if isinstance(v, Record) else copy_value(v) for k, v in self._fields.items()}

    def to_list(self) -> list[Any]:
        """The aggregate form, e.g. ``[[x, y, z], [q1, q2, q3, q4]]`` for a pose."""
        return [v.to_list() if isinstance(v, Record) else copy_value(v) for v in self._fields.values()]

    def __repr__(self) -> str:
        return f"{self.type}({format_value(self)})"


class RawBytes:
    """RAPID ``rawbytes``: up to 1024 bytes with a valid length; indices are 1-based as in RAPID."""

    MAX = 1024

    def __init__(self, data: bytes = b""):
        self.data = bytearray(data)

    def __len__(self) -> int:
        return len(self.data)

    def write(self, start: int, chunk: bytes) -> None:
        """Write at 1-based ``start``; the valid length grows to cover it (a gap is zero-filled)."""
        if start < 1 or start - 1 + len(chunk) > self.MAX:
            raise RapidError("ERR_OUTOFBND", f"rawbytes index {start} + {len(chunk)} bytes outside 1..{self.MAX}")
        if start - 1 > len(self.data):
            self.data.extend(bytes(start - 1 - len(self.data)))
        self.data[start - 1 : start - 1 + len(chunk)] = chunk

    def read(self, start: int, count: int) -> bytes:
        if start < 1 or count < 0 or start - 1 + count > len(self.data):
            raise RapidError("ERR_OUTOFBND", f"{count} bytes at {start} outside the valid length {len(self.data)}")
        return bytes(self.data[start - 1 : start - 1 + count])

    def clear(self, from_index: int = 1) -> None:
        del self.data[max(from_index, 1) - 1 :]

    def __bytes__(self) -> bytes:
        return bytes(self.data)

    def __repr__(self) -> str:
        return f"RawBytes({bytes(self.data)!r})"


class ClockVar:
    """RAPID ``clock``: accumulates running time between ClkStart and ClkStop (seconds, clock-injected)."""

    def __init__(self) -> None:
        self.started_at: float | None = None
        self.accumulated = 0.0

    def read(self, now: float) -> float:
        return self.accumulated + (now - self.started_at if self.started_at is not None else 0.0)


class Opaque:
    """A non-value type (iodev, socketdev, signaldo, wztemporary, unknown types): ``value`` is for the emulator."""

    def __init__(self, type_name: str, value: Any = None):
        self.type = type_name
        self.value = value

    def __repr__(self) -> str:
        return f"Opaque({self.type}, {self.value!r})"


def default_value(type_name: str, dims: list[int] | None = None) -> Any:
    """The value a declaration without initialiser gets (0, FALSE, "", records of defaults, arrays of those)."""
    if dims:
        return [default_value(type_name, dims[1:]) for _ in range(int(dims[0]))]
    t = type_name.lower()
    if t in NUMERIC_TYPES:
        return 0.0
    if t == "bool":
        return False
    if t == "string":
        return ""
    if t in RECORD_TYPES:
        fields = {}
        for f, ft, dflt in RECORD_TYPES[t]:
            fields[f] = default_value(ft) if dflt is None else dflt
        return Record(t, fields)
    if t == "rawbytes":
        return RawBytes()
    if t == "clock":
        return ClockVar()
    return Opaque(t)


def make_value(type_name: str, init: Any = None, dims: list[int] | None = None) -> Any:
    """A RAPID value of ``type_name`` (e.g. for a builtin to return): defaults, then the aggregate ``init``."""
    value = default_value(type_name, dims)
    return value if init is None else assign_like(value, init)


def copy_value(v: Any) -> Any:
    """Copy a value type (records, arrays); non-value objects keep their identity."""
    if isinstance(v, Record):
        return v.copy()
    if isinstance(v, list):
        return [copy_value(x) for x in v]
    return v


def from_python(v: Any) -> Any:
    """Normalise what Python code hands over: ints become floats, tuples lists; everything else as is."""
    if isinstance(v, bool) or v is None or isinstance(v, (str, Record, RawBytes, ClockVar, Opaque)):
        return v
    if isinstance(v, (int, float)):
        return float(v)
    if isinstance(v, (list, tuple)):
        return [from_python(x) for x in v]
    if hasattr(v, "__float__"):  # numpy scalars
        return float(v)
    return v


def type_of(v: Any) -> str:
    """A RAPID-ish type name for messages."""
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, float):
        return "num"
    if isinstance(v, str):
        return "string"
    if isinstance(v, (Record, Opaque)):
        return v.type
    if isinstance(v, list):
        return "array/aggregate"
    return type(v).__name__.lower()


def assign_like(old: Any, new: Any, dnum: bool = False) -> Any:
    """``new`` converted to the type and shape of ``old`` (a copy for value types), numbers rounded to a ``num``'s
    float32 unless ``dnum``; TypeError if incompatible."""
    new = from_python(new)
    if isinstance(old, bool):
        if isinstance(new, bool):
            return new
    elif isinstance(old, float):
        if isinstance(new, float):
            return new if dnum else num32(new)
    elif isinstance(old, str):
        if isinstance(new, str):
            return new
    elif isinstance(old, Record):
        if isinstance(new, Record) and new.type == old.type:
            return new.copy()
        if isinstance(new, list):
            if len(new) != len(old.fields()):
                raise TypeError(f"{old.type} has {len(old.fields())} components, the aggregate has {len(new)}")
            return Record(old.type, {k: assign_like(old[k], v) for k, v in zip(old.fields(), new)})
    elif isinstance(old, list):
        if isinstance(new, list) and len(new) == len(old):
            return [assign_like(o, n) for o, n in zip(old, new)]
        if isinstance(new, list):
            raise TypeError(f"array of {len(old)} elements cannot take {len(new)}")
    elif isinstance(old, Opaque):
        return new if isinstance(new, Opaque) else Opaque(old.type, new)
    elif type(new) is type(old):
        return new
    raise TypeError(f"cannot assign a {type_of(new)} to a {type_of(old)}")


def format_value(v: Any, nested: bool = False) -> str:
    """RAPID's text form (ValToStr, TPWrite): 6 significant digits, TRUE/FALSE, [a,b,...] for records/arrays."""
    if isinstance(v, bool):
        return "TRUE" if v else "FALSE"
    if isinstance(v, float):
        if v.is_integer() and abs(v) < 1e9:  # counters and indices print in full
            return str(int(v))
        return f"{v:.6g}".upper().replace("E+0", "E+").replace("E-0", "E-")
    if isinstance(v, str):
        return '"' + v + '"' if nested else v
    if isinstance(v, Record):
        return "[" + ",".join(format_value(x, True) for x in v._fields.values()) + "]"
    if isinstance(v, list):
        return "[" + ",".join(format_value(x, True) for x in v) + "]"
    return repr(v)


class ByteRangeError(TypeError):
    """A ``byte`` (variable, element, component, parameter) given a value outside 0..255 or a non-integer: on the
    IRC5 a run-time error that stops the program (fatal, not an ERRNO a handler could take)."""


_HAS_BYTE: dict[str, bool] = {}


def _has_byte(t: str) -> bool:
    if t == "byte":
        return True
    if t not in RECORD_TYPES:
        return False
    if t not in _HAS_BYTE:
        _HAS_BYTE[t] = False  # no recursion through a self-referencing record
        _HAS_BYTE[t] = any(_has_byte(ft) for _, ft, _ in RECORD_TYPES[t])
    return _HAS_BYTE[t]


def check_range(type_name: str | None, value: Any, where: str) -> None:
    """Raise :class:`ByteRangeError` if ``value`` (of declared type ``type_name``, any array shape) puts a value
    outside 0..255 into a ``byte``; ``where`` names the location (``tx{3}``, ``rec.b``) for the message."""
    if type_name is None or not _has_byte(type_name):
        return
    if isinstance(value, list):
        for i, v in enumerate(value):
            check_range(type_name, v, f"{where}{{{i + 1}}}")
    elif type_name == "byte":
        if not (isinstance(value, float) and value.is_integer() and 0 <= value <= 255):
            shown = format_value(value) if isinstance(value, (float, bool, str)) else repr(value)
            raise ByteRangeError(f"value error: {where} is a byte (0..255) and cannot take {shown}")
    elif isinstance(value, Record):
        for (f, ft, _), v in zip(RECORD_TYPES[type_name], value._fields.values()):
            check_range(ft, v, f"{where}.{f}")


class Cell:
    """Storage of one variable (module data, routine data, an IN parameter or a FOR loop variable); ``type`` is
    its declared RAPID type (lower case) when known: a ``byte`` (or a record with byte components) is
    range-checked on every assignment."""

    __slots__ = ("name", "value", "kind", "type")

    def __init__(self, name: str, value: Any, kind: str = "VAR", type_name: str | None = None):
        self.name, self.value, self.kind = name, value, kind  # kind: VAR PERS CONST IN FOR
        self.type = type_name.lower() if type_name else None


class Ref:
    """A writable location handed to by-reference parameters and builtins: ``ref.value`` reads/writes it.

    It is a variable (``path`` empty) or a component/element of one (``path`` of field names and 0-based indices).
    """

    __slots__ = ("cell", "path")

    def __init__(self, cell: Cell, path: tuple[str | int, ...] = ()):
        self.cell, self.path = cell, path

    @property
    def name(self) -> str:
        return self.cell.name

    def get(self) -> Any:
        v = self.cell.value
        for k in self.path:
            v = v[k]
        return v

    def set(self, new: Any) -> None:
        if self.cell.kind in ("CONST", "FOR"):
            raise TypeError(f"{self.cell.name} is {'a CONST' if self.cell.kind == 'CONST' else 'a loop variable'}")
        if not self.path:
            value = assign_like(self.cell.value, new, self.cell.type == "dnum")
            check_range(self.cell.type, value, self.cell.name)
            self.cell.value = value
            return
        parent = self.cell.value
        for k in self.path[:-1]:
            parent = parent[k]
        value = assign_like(parent[self.path[-1]], new)
        if self.cell.type is not None and _has_byte(self.cell.type):
            check_range(self._leaf_type(), value, self.location)
        parent[self.path[-1]] = value

    value = property(get, set)

    @property
    def location(self) -> str:
        """``tx{3}``, ``p.trans.x``: the variable and the path into it, 1-based as RAPID writes it."""
        return self.cell.name + "".join(f"{{{k + 1}}}" if isinstance(k, int) else f".{k}" for k in self.path)

    def _leaf_type(self) -> str | None:
        t = self.cell.type
        for k in self.path:
            if isinstance(k, str):  # a record component; an int index keeps the array's element type
                t = next((ft for f, ft, _ in RECORD_TYPES.get(t or "", []) if f == k), None)
        return t

    def child(self, key: str | int) -> Ref:
        return Ref(self.cell, self.path + (key,))

    def __repr__(self) -> str:
        return f"Ref({self.cell.name}{''.join(f'[{k!r}]' for k in self.path)} = {self.get()!r})"
