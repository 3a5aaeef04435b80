"""The :class:`Interpreter`: loads a RAPID module, owns its data, and is the Python-facing API.

Statements and error recovery live in :mod:`.statements`, calls in :mod:`.calls`, expressions in
:mod:`.expressions`; each types ``self`` as the :class:`~.contract.Runtime` protocol, which this class implements.
Frames and the control-flow signals (Return, Retry, TryNext, Propagate) are in :mod:`.frames`.
"""

from __future__ import annotations

import threading
from typing import Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.calls import CallsMixin
from maniskill_irb120.abb.emulator.rapid.errors import (
    ProgramHalt,
    RapidError,
    RapidRuntimeError,
    RapidStopped,
    errno_name,
)
from maniskill_irb120.abb.emulator.rapid.expressions import ExpressionsMixin
from maniskill_irb120.abb.emulator.rapid.frames import Frame, Propagate, Retry, Return, Routine, TryNext
from maniskill_irb120.abb.emulator.rapid.parser import parse
from maniskill_irb120.abb.emulator.rapid.registry import Builtins
from maniskill_irb120.abb.emulator.rapid.statements import StatementsMixin
from maniskill_irb120.abb.emulator.rapid.stdlib import STDLIB, SystemClock, system_data
from maniskill_irb120.abb.emulator.rapid.values import Cell, Ref, assign_like, copy_value, default_value, define_record


class Interpreter(StatementsMixin, CallsMixin, ExpressionsMixin):
    """Executes a RAPID module. ``builtins`` adds/overrides routines (see :mod:`.registry`)."""

    def __init__(
        self,
        source: str,
        builtins: Builtins | dict[str, Any] | None = None,
        *,
        clock: Any = None,
        max_retries: int = 4,
        max_statements: int | None = None,
    ):
        self.builtins = Builtins()
        self.builtins.update(STDLIB)
        if builtins is not None:
            self.builtins.update(builtins)
        self.clock = clock or SystemClock()
        self.max_retries = max_retries
        self.max_statements = max_statements
        self.statements = 0  # executed so far (all runs)
        self.tp_log: list[str] = []  # TPWrite lines
        self.err_log: list[str] = []  # ErrWrite entries
        self.connections: dict[int, str] = {}  # CONNECT intno WITH trap (recorded, traps are not run)
        self.next_errno = 0  # BookErrNo offset
        self._stop = threading.Event()
        self._stack: list[Frame] = []
        self._errno = Cell("ERRNO", 0.0, "CONST")
        self.system: dict[str, Ref] = {k: Ref(Cell(k, v, "CONST")) for k, v in system_data().items()}
        self.system["errno"] = Ref(self._errno)
        self.globals: dict[str, Ref] = {}
        self.routines: dict[str, Routine] = {}
        self.module_names: list[str] = []
        self._load(parse(source))

    # ---- public API ---------------------------------------------------------------------------------
    @property
    def errno(self) -> int:
        """ERRNO: the error number of the most recent error handled."""
        return int(self._errno.value)

    def run(self, entry: str = "main") -> str:
        """Run PROC ``entry``; returns 'completed', 'exit' (EXIT) or 'stop' (Stop)."""
        routine = self.routines.get(entry.lower())
        if routine is None or routine.kind != "PROC":
            raise RapidRuntimeError(f"no PROC {entry} in module(s) {', '.join(self.module_names)}")
        return self._top(lambda: self.call_routine(routine, [], []))[0]

    def call(self, name: str, *args: Any, **options: Any) -> Any:
        """Call a routine (PROC/FUNC/TRAP or builtin) from Python; a :class:`Ref` argument is passed by reference."""
        return self._top(lambda: self.call_from_python(name, args, options))[1]

    def get(self, name: str) -> Any:
        """A copy of module data ``name`` (num -> float, records -> Record, arrays -> list)."""
        return copy_value(self._global_ref(name).get())

    def set(self, name: str, value: Any) -> None:
        """Assign module data ``name`` (aggregates as lists, records as Record); CONSTs refuse."""
        ref = self._global_ref(name)
        try:
            ref.set(value)
        except TypeError as e:
            raise RapidRuntimeError(f"cannot set {name}: {e}") from None

    def ref(self, name: str) -> Ref:
        """A live reference to module data (pass to :meth:`call` for INOUT/VAR parameters)."""
        return self._global_ref(name)

    def request_stop(self) -> None:
        """Thread-safe: the running program raises :class:`RapidStopped` before its next statement/wait."""
        self._stop.set()

    @property
    def stop_event(self) -> threading.Event:
        """Set by request_stop(); blocking builtins should wait on it (as WaitTime does)."""
        return self._stop

    def check_stop(self) -> None:
        if self._stop.is_set():
            self._stop.clear()
            raise RapidStopped("stop requested")

    # ---- loading --------------------------------------------------------------------------------------
    def _load(self, tree: Tree) -> None:
        frame = Frame(None)
        self._stack = [frame]
        try:
            for module in tree.children:
                self.module_names.append(str(module.children[0]))
                for item in module.children[2:]:
                    if item.data == "record_decl":
                        try:
                            define_record(item.children[0], [(f.children[1], f.children[0]) for f in item.children[1:]])
                        except ValueError as e:
                            raise RapidRuntimeError(str(e), line=item.meta.line) from None
                    elif item.data == "data_decl":
                        frame.line = item.meta.line
                        self.declare(item, frame, self.globals)
                    else:
                        routine = Routine.from_tree(item)
                        if routine.key in self.routines:
                            raise RapidRuntimeError(f"routine {routine.name} is defined twice", line=routine.line)
                        self.routines[routine.key] = routine
        except RapidError as e:
            raise RapidRuntimeError(f"error initialising module data: {e}", errno=e.errno, line=frame.line) from None
        finally:
            self._stack = []

    def declare(self, decl: Tree, frame: Frame, scope: dict[str, Any]) -> None:
        """Create the variable of a ``data_decl`` (default value, then the initialiser if any) in ``scope``."""
        _, storage, type_name, name, dims, init = decl.children
        shape = [self._dim(self.eval(e, frame)) for e in dims.children] if dims is not None else None
        value = default_value(type_name, shape)
        if init is not None:
            try:
                value = assign_like(value, self.eval(init, frame))
            except TypeError as e:
                raise self.fault(f"initialiser of {name}: {e}") from None
        scope[name.lower()] = Ref(Cell(str(name), value, storage.children[0].upper()))

    def _dim(self, v: Any) -> int:
        if not isinstance(v, float) or not v.is_integer() or v < 1:
            raise self.fault(f"array dimension must be a positive integer, got {v!r}")
        return int(v)

    # ---- names ----------------------------------------------------------------------------------------
    def lookup(self, name: str, frame: Frame) -> Ref:
        if name in frame.vars:
            ref = frame.vars[name]
            if ref is None:
                raise RapidError("ERR_NOTPRES", f"optional parameter {name} was not given")
            return ref
        ref = self.globals.get(name) or self.system.get(name)
        if ref is None:
            raise self.fault(f"undefined name {name}")
        return ref

    def _global_ref(self, name: str) -> Ref:
        ref = self.globals.get(name.lower()) or self.system.get(name.lower())
        if ref is None:
            raise RapidRuntimeError(f"no module data named {name}")
        return ref

    def fault(self, message: str) -> RapidRuntimeError:
        """A fatal error located at the current statement (callers ``raise self.fault(...)``)."""
        frame = self._stack[-1] if self._stack else None
        return RapidRuntimeError(message, routine=frame.name if frame else None, line=frame.line if frame else None)

    def store(self, ref: Ref, value: Any) -> None:
        try:
            ref.set(value)
        except TypeError as e:
            raise self.fault(f"cannot assign to {ref.name}: {e}") from None

    # ---- execution ------------------------------------------------------------------------------------
    def _top(self, fn: Any) -> tuple[str, Any]:
        saved, self._stack = self._stack, []  # saved: call() may be re-entered from a builtin
        try:
            return "completed", fn()
        except ProgramHalt as h:
            return h.kind, None
        except (RapidError, Propagate) as e:
            err = e.error if isinstance(e, Propagate) else e
            detail = f": {err.message}" if err.message else ""
            msg = f"unhandled RAPID error {err.errno} ({errno_name(err.errno)}){detail}"
            raise RapidRuntimeError(msg, errno=err.errno, routine=err.routine, line=err.line) from None
        except (Retry, TryNext, Return) as e:  # pragma: no cover - caught in routines
            raise RapidRuntimeError(f"misplaced {type(e).__name__.upper()}") from None
        finally:
            self._stack = saved

    def tick(self) -> None:
        """Called before every statement: honours request_stop() and the statement budget."""
        self.check_stop()
        self.statements += 1
        if self.max_statements is not None and self.statements > self.max_statements:
            raise RapidStopped(f"statement budget of {self.max_statements} exhausted")
