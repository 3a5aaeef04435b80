"""Routines and calls (a mixin of :class:`Interpreter`): parameter binding, by-reference arguments, builtins."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.errors import ProgramHalt, RapidError, RapidRuntimeError, RapidStopped
from maniskill_irb120.abb.emulator.rapid.registry import Builtin
from maniskill_irb120.abb.emulator.rapid.values import Cell, Ref, assign_like, copy_value, default_value, from_python

if TYPE_CHECKING:
    from maniskill_irb120.abb.emulator.rapid.interpreter import Interpreter


@dataclass
class Param:
    """A routine parameter; ``group`` numbers alternatives (``\\a | \\b``), ``array`` is ``{*}``."""

    name: str
    type: str
    mode: str  # IN, INOUT, VAR, PERS
    optional: bool = False
    group: int = 0
    array: bool = False

    @property
    def key(self) -> str:
        return self.name.lower()


@dataclass
class Routine:
    """A PROC, FUNC or TRAP; BACKWARD and UNDO sections are parsed but not run."""

    name: str
    kind: str
    rtype: str | None
    params: list[Param]
    decls: list[Tree]
    body: Tree
    handler: Tree | None
    handler_filter: list[str] | None
    line: int

    @property
    def key(self) -> str:
        return self.name.lower()

    def param(self, key: str) -> Param | None:
        return next((p for p in self.params if p.key == key), None)

    @classmethod
    def from_tree(cls, t: Tree) -> Routine:
        kind = t.data.upper()
        if kind == "FUNC":
            _, rtype, name, _, params, body = t.children
        elif kind == "PROC":
            _, name, params, body = t.children
            rtype = None
        else:
            _, name, body = t.children
            rtype, params = None, None
        decls, stmts, _backward, handler, _undo = body.children
        plist: list[Param] = []
        for group, p in enumerate(params.children if params is not None else [], start=1):
            alts = p.children if p.data == "opt_param" else [p]
            for alt in alts:
                mode, ptype, pname, star = alt.children
                mode = mode.children[0].upper() if mode is not None else "IN"
                plist.append(Param(str(pname), ptype.lower(), mode, p.data == "opt_param", group, star is not None))
        flt = handler.children[0] if handler is not None else None
        return cls(
            name=str(name),
            kind=kind,
            rtype=rtype.lower() if rtype else None,
            params=plist,
            decls=list(decls.children),
            body=stmts,
            handler=handler.children[1] if handler is not None else None,
            handler_filter=[str(n) for n in flt.children] if flt is not None else None,
            line=t.meta.line,
        )


class Frame:
    """One routine activation: its variables (None = optional parameter not given) and handler state."""

    __slots__ = ("routine", "vars", "line", "in_handler", "error")

    def __init__(self, routine: Routine | None, variables: dict[str, Ref | None] | None = None):
        self.routine = routine
        self.vars: dict[str, Ref | None] = variables if variables is not None else {}
        self.line: int | None = routine.line if routine else None
        self.in_handler = False
        self.error: RapidError | None = None

    @property
    def name(self) -> str:
        return self.routine.name if self.routine else "<module data>"


class Return(Exception):
    def __init__(self, value: Any):
        self.value = value


class Retry(Exception):
    pass


class TryNext(Exception):
    pass


class Propagate(Exception):
    """An error leaving a routine's handler: it skips the routine's other statements and reaches the caller."""

    def __init__(self, error: RapidError):
        self.error = error


class TreeArg:
    """An argument written in RAPID: evaluated in the caller's frame (or resolved to a Ref for by-reference)."""

    __slots__ = ("interp", "tree", "frame")

    def __init__(self, interp: Interpreter, tree: Tree, frame: Frame):
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


Args = tuple[list[Any], list[tuple[str, Any]]]  # positional arg sources, (option name, source or None=switch)


class CallsMixin:
    """call_statement / call_function for RAPID call sites, call_from_python for Interpreter.call."""

    def split_args(self: Interpreter, args: Tree | None, frame: Frame) -> Args:
        positional: list[Any] = []
        options: list[tuple[str, Any]] = []
        for a in args.children if args is not None else []:
            if a.data == "opt_arg":
                name, expr = a.children
                options.append((str(name), TreeArg(self, expr, frame) if expr is not None else None))
            elif a.data == "cond_arg":  # \Opt?param: passed on only if the caller's own optional param was given
                name, pname = a.children
                if pname.lower() not in frame.vars:
                    raise self.fault(f"{pname} in \\{name}?{pname} is not a parameter of {frame.name}")
                ref = frame.vars[pname.lower()]
                if ref is not None:
                    p = frame.routine.param(pname.lower()) if frame.routine else None
                    options.append((str(name), None if p is not None and p.type == "switch" else ValueArg(ref)))
            else:
                positional.append(TreeArg(self, a, frame))
        return positional, options

    def call_statement(self: Interpreter, st: Tree, frame: Frame) -> None:
        name, args = st.children
        routine = self.routines.get(name.lower())
        if routine is not None:
            if routine.kind != "PROC":
                raise self.fault(f"{routine.kind} {routine.name} cannot be called as a procedure")
            self.call_routine(routine, *self.split_args(args, frame))
            return
        builtin = self.builtins.get(name)
        if builtin is not None:
            self.call_builtin(builtin, *self.split_args(args, frame))
        elif name.lower() == "waituntil":  # its condition is re-evaluated, so it cannot be an ordinary builtin
            self.wait_until(*self.split_args(args, frame))
        else:
            raise self.fault(f"unknown procedure {name}")

    def call_function(self: Interpreter, t: Tree, frame: Frame) -> Any:
        name, args = t.children
        if name.lower() == "present":
            return self._present(args, frame)
        routine = self.routines.get(name.lower())
        if routine is not None:
            if routine.kind != "FUNC":
                raise self.fault(f"{routine.kind} {routine.name} is not a function")
            return self.call_routine(routine, *self.split_args(args, frame))
        builtin = self.builtins.get(name)
        if builtin is None:
            raise self.fault(f"unknown function {name}")
        result = self.call_builtin(builtin, *self.split_args(args, frame))
        if result is None:
            raise self.fault(f"{name} returned no value (is it a procedure?)")
        return from_python(result)

    def _present(self: Interpreter, args: Tree | None, frame: Frame) -> bool:
        arg = args.children[0] if args is not None and len(args.children) == 1 else None
        if arg is None or arg.data != "target" or len(arg.children) != 1:
            raise self.fault("Present needs one parameter name")
        key = arg.children[0].lower()
        if frame.routine is None or frame.routine.param(key) is None:
            raise self.fault(f"Present: {arg.children[0]} is not a parameter of {frame.name}")
        return frame.vars.get(key) is not None

    def call_from_python(self: Interpreter, name: str, args: tuple, options: dict[str, Any]) -> Any:
        routine = self.routines.get(name.lower())
        if routine is None:
            builtin = self.builtins.get(name)
            if builtin is None:
                raise RapidRuntimeError(f"no routine or builtin named {name}")
            return from_python(self.call_builtin(builtin, [ValueArg(a) for a in args], _py_opts(options, None)))
        return copy_value(self.call_routine(routine, [ValueArg(a) for a in args], _py_opts(options, routine)))

    def call_routine(self: Interpreter, routine: Routine, positional: list[Any], options: list[tuple[str, Any]]) -> Any:
        frame = Frame(routine, self._bind(routine, positional, options))
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
                return r.value if isinstance(r.value, list) else assign_like(default_value(routine.rtype), r.value)
            except TypeError as e:
                raise self.fault(f"FUNC {routine.name} returns {routine.rtype}: {e}") from None
        except Propagate as p:
            raise p.error from None
        finally:
            self._stack.pop()

    def _bind(self: Interpreter, routine: Routine, positional: list[Any], options: list[tuple[str, Any]]) -> dict:
        required = [p for p in routine.params if not p.optional]
        if len(positional) != len(required):
            raise self.fault(f"{routine.name} takes {len(required)} argument(s), {len(positional)} given")
        bound: dict[str, Ref | None] = {p.key: self._bind_one(routine, p, a) for p, a in zip(required, positional)}
        bound.update({p.key: None for p in routine.params if p.optional})
        used: dict[int, str] = {}
        for name, arg in options:
            p = routine.param(name.lower())
            if p is None or not p.optional:
                raise self.fault(f"{routine.name} has no optional parameter \\{name}")
            if p.group in used:
                raise self.fault(f"\\{name} and \\{used[p.group]} of {routine.name} exclude each other")
            used[p.group] = name
            if p.type == "switch":
                if arg is not None:
                    raise self.fault(f"switch \\{name} takes no value")
                bound[p.key] = Ref(Cell(p.name, True, "CONST"))
            elif arg is None:
                raise self.fault(f"\\{name} of {routine.name} needs a value (\\{name}:=...)")
            else:
                bound[p.key] = self._bind_one(routine, p, arg)
        return bound

    def _bind_one(self: Interpreter, routine: Routine, p: Param, arg: Any) -> Ref:
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
                value = assign_like(default_value(p.type), current)
        except TypeError as e:
            raise self.fault(f"{what}: {e}") from None
        return ref if p.mode != "IN" else Ref(Cell(p.name, current if p.array else value, "IN"))

    def call_builtin(self: Interpreter, b: Builtin, positional: list[Any], options: list[tuple[str, Any]]) -> Any:
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
        except (RapidError, RapidRuntimeError, RapidStopped, ProgramHalt, Propagate):
            raise
        except Exception as e:
            raise self.fault(f"{b.name} failed: {type(e).__name__}: {e}") from e


def _py_opts(options: dict[str, Any], routine: Routine | None) -> list[tuple[str, Any]]:
    out = []
    for k, v in options.items():
        p = routine.param(k.lower()) if routine else None
        if p is not None and p.type == "switch":
            if v:
                out.append((k, None))
        else:
            out.append((k, ValueArg(v)))
    return out
