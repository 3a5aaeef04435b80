"""Routines and calls (a mixin typed against :class:`~.contract.Runtime`): parameter binding, by-reference
arguments, builtins. See docs/rapid_subset.md.
"""

from __future__ import annotations

from typing import Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.contract import Args, Options, Runtime
from maniskill_irb120.abb.emulator.rapid.errors import ProgramHalt, RapidError, RapidRuntimeError, RapidStopped
from maniskill_irb120.abb.emulator.rapid.execution import PPToMain
from maniskill_irb120.abb.emulator.rapid.frames import Frame, Param, Propagate, Return, Routine
from maniskill_irb120.abb.emulator.rapid.registry import Builtin
from maniskill_irb120.abb.emulator.rapid.values import (
    ByteRangeError,
    Cell,
    Ref,
    assign_like,
    check_range,
    copy_value,
    default_value,
    from_python,
)


class TreeArg:
    """An argument written in RAPID: evaluated in the caller's frame (or resolved to a Ref for by-reference)."""

    __slots__ = ("interp", "tree", "frame")

    def __init__(self, interp: Runtime, tree: Tree, frame: Frame):
        self.interp, self.tree, self.frame = interp, tree, frame

    def value(self) -> Any:
        return copy_value(self.interp.eval(self.tree, self.frame))

    def ref(self, what: str) -> Ref:
        if self.tree.data != "target":
            raise self.interp.fault(f"{what} must be a variable, not an expression")
        return self.interp.resolve(self.tree, self.frame)


class ValueArg:
    """An argument given from Python: a Ref is passed by reference, a plain value through a temporary variable."""

    __slots__ = ("v",)

    def __init__(self, v: Any):
        self.v = v

    def value(self) -> Any:
        return copy_value(self.v.get()) if isinstance(self.v, Ref) else from_python(self.v)

    def ref(self, what: str) -> Ref:
        return self.v if isinstance(self.v, Ref) else Ref(Cell("<python>", from_python(self.v)))


class CallsMixin:
    """call_statement / call_function for RAPID call sites, call_from_python for Interpreter.call."""

    def call_statement(self: Runtime, st: Tree, frame: Frame) -> None:
        name, args = st.children
        routine = self.find_routine(name, frame.module)
        if routine is not None:
            if routine.kind != "PROC":
                raise self.fault(f"{routine.kind} {routine.name} cannot be called as a procedure")
            self.call_routine(routine, *_split_args(self, args, frame))
            return
        builtin = self.builtins.get(name)
        if builtin is not None:
            self.call_builtin(builtin, *_split_args(self, args, frame))
        elif name.lower() == "waituntil":  # its condition is re-evaluated, so it cannot be an ordinary builtin
            self.wait_until(*_split_args(self, args, frame))
        else:
            raise self.fault(f"unknown procedure {name}")

    def call_function(self: Runtime, t: Tree, frame: Frame) -> Any:
        name, args = t.children
        if name.lower() == "present":
            return _present(self, args, frame)
        routine = self.find_routine(name, frame.module)
        if routine is not None:
            if routine.kind != "FUNC":
                raise self.fault(f"{routine.kind} {routine.name} is not a function")
            return self.call_routine(routine, *_split_args(self, args, frame))
        builtin = self.builtins.get(name)
        if builtin is None:
            raise self.fault(f"unknown function {name}")
        result = self.call_builtin(builtin, *_split_args(self, args, frame))
        if result is None:
            raise self.fault(f"{name} returned no value (is it a procedure?)")
        return from_python(result)

    def call_from_python(self: Runtime, name: str, args: tuple, options: dict[str, Any]) -> Any:
        routine = self.find_routine_py(name)
        if routine is None:
            builtin = self.builtins.get(name)
            if builtin is None:
                raise RapidRuntimeError(f"no routine or builtin named {name}")
            return from_python(self.call_builtin(builtin, [ValueArg(a) for a in args], _py_opts(options, None)))
        return copy_value(self.call_routine(routine, [ValueArg(a) for a in args], _py_opts(options, routine)))

    def call_routine(self: Runtime, routine: Routine, positional: Args, options: Options) -> Any:
        frame = Frame(routine, _bind(self, routine, positional, options))
        self._stack.append(frame)
        try:
            for decl in routine.decls:
                frame.line = decl.meta.line
                self.declare(decl, frame, frame.vars)
            self.block(routine.body, frame)
            if routine.kind == "FUNC":
                raise self.fault(f"FUNC {routine.name} ended without RETURN")
            return None
        except Return as r:
            if routine.kind != "FUNC":
                if r.value is not None:
                    raise self.fault(f"RETURN with a value in {routine.kind} {routine.name}") from None
                return None
            if r.value is None:
                raise self.fault(f"RETURN without a value in FUNC {routine.name}") from None
            try:
                if isinstance(r.value, list):
                    return r.value
                return assign_like(default_value(routine.rtype), r.value, routine.rtype == "dnum")
            except TypeError as e:
                raise self.fault(f"FUNC {routine.name} returns {routine.rtype}: {e}") from None
        except Propagate as p:
            raise p.error from None
        except PPToMain:
            if routine.undo is not None:  # innermost first, as the pointer leaves each routine
                frame.in_handler = True
                try:
                    self.block(routine.undo, frame)
                except (RapidError, Propagate) as e:  # an UNDO that fails does not stop the others
                    err = e.error if isinstance(e, Propagate) else e
                    self.err_log.append(f"UNDO of {routine.name} failed: {err}")
            raise
        finally:
            self._stack.pop()

    def call_builtin(self: Runtime, b: Builtin, positional: Args, options: Options) -> Any:
        pos = [a.ref(f"argument {i + 1} of {b.name}") if i in b.refs else a.value() for i, a in enumerate(positional)]
        kw: dict[str, Any] = {}
        for name, arg in options:
            key = b.keyword(name)
            if key is None:
                raise self.fault(f"{b.name} has no optional argument \\{name}")
            if arg is None:
                kw[key] = True
            else:
                kw[key] = arg.ref(f"\\{name} of {b.name}") if name.lower() in b.refs else arg.value()
        try:
            return b.fn(self, *pos, **kw) if b.with_interp else b.fn(*pos, **kw)
        except (RapidError, RapidRuntimeError, RapidStopped, ProgramHalt, Propagate, PPToMain):
            raise
        except Exception as e:
            raise self.fault(f"{b.name} failed: {type(e).__name__}: {e}") from e


def _split_args(rt: Runtime, args: Tree | None, frame: Frame) -> tuple[Args, Options]:
    """The argument sources of a RAPID call site: positional, and (name, source or None=switch) options."""
    positional: list[Any] = []
    options: list[tuple[str, Any]] = []
    for a in args.children if args is not None else []:
        if a.data == "opt_arg":
            name, expr = a.children
            options.append((str(name), TreeArg(rt, expr, frame) if expr is not None else None))
        elif a.data == "cond_arg":  # \Opt?param: passed on only if the caller's own optional param was given
            name, pname = a.children
            if pname.lower() not in frame.vars:
                raise rt.fault(f"{pname} in \\{name}?{pname} is not a parameter of {frame.name}")
            ref = frame.vars[pname.lower()]
            if ref is not None:
                p = frame.routine.param(pname.lower()) if frame.routine else None
                options.append((str(name), None if p is not None and p.type == "switch" else ValueArg(ref)))
        else:
            positional.append(TreeArg(rt, a, frame))
    return positional, options


def _present(rt: Runtime, args: Tree | None, frame: Frame) -> bool:
    arg = args.children[0] if args is not None and len(args.children) == 1 else None
    if arg is None or arg.data != "target" or len(arg.children) != 1:
        raise rt.fault("Present needs one parameter name")
    key = arg.children[0].lower()
    if frame.routine is None or frame.routine.param(key) is None:
        raise rt.fault(f"Present: {arg.children[0]} is not a parameter of {frame.name}")
    return frame.vars.get(key) is not None


def _bind(rt: Runtime, routine: Routine, positional: Args, options: Options) -> dict:
    required = [p for p in routine.params if not p.optional]
    if len(positional) != len(required):
        raise rt.fault(f"{routine.name} takes {len(required)} argument(s), {len(positional)} given")
    bound: dict[str, Ref | None] = {p.key: _bind_one(rt, routine, p, a) for p, a in zip(required, positional)}
    bound.update({p.key: None for p in routine.params if p.optional})
    used: dict[int, str] = {}
    for name, arg in options:
        p = routine.param(name.lower())
        if p is None or not p.optional:
            raise rt.fault(f"{routine.name} has no optional parameter \\{name}")
        if p.group in used:
            raise rt.fault(f"\\{name} and \\{used[p.group]} of {routine.name} exclude each other")
        used[p.group] = name
        if p.type == "switch":
            if arg is not None:
                raise rt.fault(f"switch \\{name} takes no value")
            bound[p.key] = Ref(Cell(p.name, True, "CONST"))
        elif arg is None:
            raise rt.fault(f"\\{name} of {routine.name} needs a value (\\{name}:=...)")
        else:
            bound[p.key] = _bind_one(rt, routine, p, arg)
    return bound


def _bind_one(rt: Runtime, routine: Routine, p: Param, arg: Any) -> Ref:
    what = f"argument {p.name} of {routine.name}"
    if p.mode != "IN":
        ref = arg.ref(f"{p.mode} {what}")
        current = ref.get()
    else:
        current = arg.value()
    try:
        if p.array:
            if not isinstance(current, list):
                raise TypeError(f"expected an array, got {current!r}")
        else:
            value = assign_like(default_value(p.type), current, p.type == "dnum")
    except TypeError as e:
        raise rt.fault(f"{what}: {e}") from None
    if p.mode != "IN":
        return ref
    try:
        check_range(p.type, current if p.array else value, f"{p.name} of {routine.name}")
    except ByteRangeError as e:
        raise rt.fault(str(e)) from None
    return Ref(Cell(p.name, current if p.array else value, "IN", p.type))


def _py_opts(options: dict[str, Any], routine: Routine | None) -> Options:
    out = []
    for k, v in options.items():
        p = routine.param(k.lower()) if routine else None
        if p is not None and p.type == "switch":
            if v:
                out.append((k, None))
        else:
            out.append((k, ValueArg(v)))
    return out
