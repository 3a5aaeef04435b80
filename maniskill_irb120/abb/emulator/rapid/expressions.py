"""Expression evaluation and variable resolution (a mixin typed against :class:`~.contract.Runtime`), with RAPID's
operator rules. See docs/rapid_subset.md.
"""

from __future__ import annotations

import math
import re
from typing import Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.contract import Runtime
from maniskill_irb120.abb.emulator.rapid.errors import RapidError
from maniskill_irb120.abb.emulator.rapid.frames import Frame
from maniskill_irb120.abb.emulator.rapid.values import (
    Record,
    Ref,
    assign_like,
    copy_value,
    is_num32,
    is_num32_range,
    num32,
    type_of,
)

_ESCAPE = re.compile(r'""|\\\\|\\([0-9a-fA-F]{2})')


def decode_string(token: str) -> str:
    """A RAPID string literal's text: ``""`` is a quote, ``\\\\`` a backslash, ``\\hh`` a character code."""
    return _ESCAPE.sub(lambda m: '"' if m[0] == '""' else "\\" if m[0] == "\\\\" else chr(int(m[1], 16)), token[1:-1])


def _pos(v: Any) -> bool:
    return isinstance(v, Record) and v.type == "pos"


def _mkpos(x: float, y: float, z: float) -> Record:
    return Record("pos", {"x": x, "y": y, "z": z})


class ExpressionsMixin:
    """``eval(tree, frame)``, ``condition(tree, frame)`` and ``resolve(target, frame) -> Ref``."""

    def eval(self: Runtime, t: Tree, frame: Frame) -> Any:
        """The value of an expression; records/arrays read from variables are the live objects (copy to keep)."""
        kind = t.data
        if kind == "target":
            return self.resolve(t, frame).get()
        if kind == "number":
            text = t.children[0]
            v = float(int(text, 16)) if text[:2] in ("0x", "0X") else float(text)
            # a literal is a num; an integer a float32 cannot hold exactly is a dnum's and stays (verify)
            return v if not is_num32_range(v) or (v.is_integer() and not is_num32(v)) else num32(v)
        if kind == "string":
            return decode_string(t.children[0])
        if kind == "true" or kind == "false":
            return kind == "true"
        if kind == "func_call":
            return self.call_function(t, frame)
        if kind == "aggregate":
            return [copy_value(self.eval(c, frame)) for c in t.children]
        if kind in ("and_", "or_", "xor"):
            return _logic(self, kind, t, frame)
        if kind == "not_":
            return not _bool(self, self.eval(t.children[0], frame), "NOT")
        if kind == "neg":
            v = self.eval(t.children[0], frame)
            if isinstance(v, float):
                return -v
            if _pos(v):
                return _mkpos(-v.x, -v.y, -v.z)
            raise self.fault(f"cannot negate a {type_of(v)}")
        if kind == "compare":
            return compare(self, self.eval(t.children[0], frame), str(t.children[1]), self.eval(t.children[2], frame))
        a, b = self.eval(t.children[0], frame), self.eval(t.children[1], frame)
        return _arith(self, kind, a, b)

    def condition(self: Runtime, t: Tree, frame: Frame) -> bool:
        return _bool(self, self.eval(t, frame), "a condition")

    def resolve(self: Runtime, t: Tree, frame: Frame) -> Ref:
        """The location a ``target`` (``a``, ``a{i}``, ``p.trans.x``) denotes, bounds- and field-checked."""
        ref = self.lookup(t.children[0].lower(), frame)
        for sel in t.children[1:]:
            v = ref.get()
            if sel.data == "field":
                name = sel.children[0]
                if not isinstance(v, Record) or name.lower() not in v.fields():
                    raise self.fault(f"{type_of(v)} has no component {name}")
                ref = ref.child(name.lower())
                continue
            for e in sel.children:
                i = self.eval(e, frame)
                if not isinstance(v, list):
                    raise self.fault(f"{ref.name} is not an array (or has fewer dimensions)")
                if not isinstance(i, float) or not i.is_integer():
                    raise self.fault(f"array index must be an integer num, got {i!r}")
                if not 1 <= i <= len(v):
                    raise RapidError("ERR_OUTOFBND", f"index {int(i)} outside {ref.name}{{1..{len(v)}}}")
                ref = ref.child(int(i) - 1)
                v = v[int(i) - 1]
        return ref


def _bool(rt: Runtime, v: Any, what: str) -> bool:
    if not isinstance(v, bool):
        raise rt.fault(f"{what} needs a bool, got a {type_of(v)}")
    return v


def _logic(rt: Runtime, kind: str, t: Tree, frame: Frame) -> bool:
    a = _bool(rt, rt.eval(t.children[0], frame), kind.rstrip("_").upper())
    if kind == "and_" and not a:
        return False
    if kind == "or_" and a:
        return True
    b = _bool(rt, rt.eval(t.children[1], frame), kind.rstrip("_").upper())
    return a != b if kind == "xor" else b


def compare(rt: Runtime, a: Any, op: str, b: Any) -> bool:
    """RAPID's ``= <> < > <= >=`` (also TEST/CASE matching); ``=`` between a record and an aggregate compares fields."""
    if op in ("=", "<>"):
        if isinstance(b, Record) and isinstance(a, list):
            a, b = b, a
        if isinstance(a, Record) and isinstance(b, list):  # record = aggregate: compare in the record's shape
            try:
                b = assign_like(a, b)
            except TypeError:
                pass
        if type_of(a) != type_of(b):
            raise rt.fault(f"cannot compare a {type_of(a)} with a {type_of(b)}")
        return (a == b) == (op == "=")
    if not (isinstance(a, float) and isinstance(b, float)):
        raise rt.fault(f"'{op}' needs two num values, got {type_of(a)} and {type_of(b)}")
    return {"<": a < b, ">": a > b, "<=": a <= b, ">=": a >= b}[op]


def _arith(rt: Runtime, kind: str, a: Any, b: Any) -> Any:
    nums = isinstance(a, float) and isinstance(b, float)
    r = _arith_double(rt, kind, a, b)
    # num arithmetic is float32 on the IRC5 (docs/reference.md): the result rounded, unless an operand is not a float32
    # (a dnum's, a clock reading, a literal like 0.1) and the result is kept for a dnum or rounded when stored
    return num32(r) if nums and is_num32(a) and is_num32(b) else r


def _arith_double(rt: Runtime, kind: str, a: Any, b: Any) -> Any:
    nums = isinstance(a, float) and isinstance(b, float)
    if kind == "add":
        if nums or (isinstance(a, str) and isinstance(b, str)):
            return a + b
        if _pos(a) and _pos(b):
            return _mkpos(a.x + b.x, a.y + b.y, a.z + b.z)
    elif kind == "sub":
        if nums:
            return a - b
        if _pos(a) and _pos(b):
            return _mkpos(a.x - b.x, a.y - b.y, a.z - b.z)
    elif kind == "mul":
        if nums:
            return a * b
        if isinstance(a, float) and _pos(b):
            a, b = b, a
        if _pos(a) and isinstance(b, float):
            return _mkpos(a.x * b, a.y * b, a.z * b)
    elif kind == "div":
        if isinstance(b, float) and b == 0.0 and (isinstance(a, float) or _pos(a)):
            raise RapidError("ERR_DIVZERO", "division by zero")
        if nums:
            return a / b
        if _pos(a) and isinstance(b, float):
            return _mkpos(a.x / b, a.y / b, a.z / b)
    elif nums:  # DIV, MOD: integer operands, truncation towards zero (the remainder takes a's sign)
        if not (a.is_integer() and b.is_integer()):
            raise RapidError("ERR_ARGVALERR", f"{kind.upper()} needs integer operands, got {a} and {b}")
        if b == 0.0:
            raise RapidError("ERR_DIVZERO", "division by zero")
        q = float(math.trunc(a / b)) if abs(a) < 2**52 else float(int(a) // int(b))
        return q if kind == "intdiv" else a - b * q
    op = {"add": "+", "sub": "-", "mul": "*", "div": "/", "intdiv": "DIV", "mod": "MOD"}[kind]
    raise rt.fault(f"operator '{op}' is not defined for {type_of(a)} and {type_of(b)}")
