"""Routines, activation frames and the control-flow signals the interpreter's parts pass to each other. Plain
data, no behaviour beyond building a :class:`Routine` from its parse tree. See docs/rapid_subset.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.errors import RapidError
from maniskill_irb120.abb.emulator.rapid.values import Ref


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
    """A PROC, FUNC or TRAP; its UNDO section runs when PP to main unwinds it; BACKWARD is parsed, not run."""

    name: str
    kind: str
    rtype: str | None
    params: list[Param]
    decls: list[Tree]
    body: Tree
    handler: Tree | None
    handler_filter: list[str] | None
    line: int
    undo: Tree | None = None  # UNDO: run when the program pointer leaves the routine by PP to main
    module: str = ""  # the module that declares it (its LOCAL names are visible from here)
    local: bool = False  # declared LOCAL: visible only inside its module

    @property
    def key(self) -> str:
        return self.name.lower()

    def param(self, key: str) -> Param | None:
        return next((p for p in self.params if p.key == key), None)

    @classmethod
    def from_tree(cls, t: Tree, module: str = "") -> Routine:
        kind = t.data.upper()
        scope = t.children[0]
        if kind == "FUNC":
            _, rtype, name, _, params, body = t.children
        elif kind == "PROC":
            _, name, params, body = t.children
            rtype = None
        else:
            _, name, body = t.children
            rtype, params = None, None
        decls, stmts, _backward, handler, undo = body.children
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
            undo=undo.children[0] if undo is not None else None,
            module=module,
            local=scope is not None and scope.children[0].upper() == "LOCAL",
        )


class Frame:
    """One routine activation: its variables (None = optional parameter not given) and handler state; ``module``
    is where names are looked up (the routine's module; for module data, the module being initialised)."""

    __slots__ = ("routine", "vars", "line", "in_handler", "error", "module")

    def __init__(
        self, routine: Routine | None, variables: dict[str, Ref | None] | None = None, module: str | None = None
    ):
        self.routine = routine
        self.module = (routine.module if routine else "") if module is None else module
        self.vars: dict[str, Ref | None] = variables if variables is not None else {}
        self.line: int | None = routine.line if routine else None
        self.in_handler = False
        self.error: RapidError | None = None

    @property
    def name(self) -> str:
        return self.routine.name if self.routine else "<module data>"


# ---- control-flow signals (exceptions that are not RAPID errors) ------------------------------------------------
class Return(Exception):
    """RETURN [value]: leaves the routine; caught by ``call_routine``."""

    def __init__(self, value: Any):
        self.value = value


class Retry(Exception):
    """RETRY in an ERROR handler: re-run the failing statement; caught by ``execute``."""


class TryNext(Exception):
    """TRYNEXT in an ERROR handler: go on after the failing statement; caught by ``execute``."""


class Propagate(Exception):
    """An error leaving a routine's handler: it skips the routine's other statements and reaches the caller."""

    def __init__(self, error: RapidError):
        self.error = error
