"""The :class:`Interpreter`: loads a RAPID task's modules, owns its data, and is the Python-facing API.
Statements and error recovery live in :mod:`.statements`, calls in :mod:`.calls`, expressions in :mod:`.expressions`,
each typing ``self`` as :class:`~.contract.Runtime`; frames and control-flow signals in :mod:`.frames`.
See docs/rapid_subset.md.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.calls import CallsMixin
from maniskill_irb120.abb.emulator.rapid.errors import (
    ProgramHalt,
    RapidError,
    RapidLoadError,
    RapidRuntimeError,
    errno_name,
)
from maniskill_irb120.abb.emulator.rapid.execution import ExecutionMixin
from maniskill_irb120.abb.emulator.rapid.expressions import ExpressionsMixin
from maniskill_irb120.abb.emulator.rapid.frames import Frame, Propagate, Retry, Return, Routine, TryNext
from maniskill_irb120.abb.emulator.rapid.options import declared_names, missing_options, parse_options
from maniskill_irb120.abb.emulator.rapid.parser import parse
from maniskill_irb120.abb.emulator.rapid.registry import Builtins
from maniskill_irb120.abb.emulator.rapid.statements import StatementsMixin
from maniskill_irb120.abb.emulator.rapid.stdlib import STDLIB, SystemClock, system_data
from maniskill_irb120.abb.emulator.rapid.values import (
    ByteRangeError,
    Cell,
    Ref,
    assign_like,
    check_range,
    copy_value,
    default_value,
    define_record,
)


class Interpreter(ExecutionMixin, StatementsMixin, CallsMixin, ExpressionsMixin):
    """Executes the RAPID modules of one task. ``builtins`` adds/overrides routines (see :mod:`.registry`).

    ``source`` is one source text or several (each may hold several modules; line numbers count per text).
    Routine and data names are global to the task unless ``LOCAL`` (``TASK`` is treated as global). Loading
    refuses (:class:`RapidLoadError`) a global name declared twice, and, when ``options`` is given (installed
    RobotWare option ids such as ``"616-1"``; ``()``: none), any use of a name whose option is missing
    (:mod:`.options`). ``options=None`` skips that check. Stop/start, PP to main and ``statement_cost_s`` (the
    controller time of one statement): :mod:`.execution`. ``host``: the controller that runs the task; builtins
    registered ``with_interp`` reach it as ``interp.host``.
    """

    def __init__(
        self,
        source: str | Sequence[str],
        builtins: Builtins | dict[str, Any] | None = None,
        *,
        clock: Any = None,
        max_retries: int = 4,
        max_statements: int | None = None,
        options: Iterable[str] | None = None,
        statement_cost_s: float = 0.0,
        host: Any = None,
    ):
        self.host = host  # the controller running this task: what its builtins act on (None: a bare interpreter)
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
        self._init_execution(statement_cost_s)
        self._stack: list[Frame] = []
        self._errno = Cell("ERRNO", 0.0, "CONST")
        self.system: dict[str, Ref] = {k: Ref(Cell(k, v, "CONST")) for k, v in system_data().items()}
        self.system["errno"] = Ref(self._errno)
        self.options = None if options is None else parse_options(options)
        self.globals: dict[str, Ref] = {}  # task-wide module data
        self.routines: dict[str, Routine] = {}  # task-wide routines
        self.local_data: dict[str, dict[str, Ref]] = {}  # module (lower case) -> its LOCAL data
        self.local_routines: dict[str, dict[str, Routine]] = {}  # module (lower case) -> its LOCAL routines
        self.module_names: list[str] = []
        self._owner: dict[str, str] = {}  # global name -> its module (lower case)
        sources = [source] if isinstance(source, str) else list(source)
        self._load([m for tree in map(parse, sources) for m in tree.children])

    # ---- public API ---------------------------------------------------------------------------------
    @property
    def errno(self) -> int:
        """ERRNO: the error number of the most recent error handled."""
        return int(self._errno.value)

    def run(self, entry: str = "main") -> str:
        """Run PROC ``entry`` (``"Module:name"`` for a LOCAL one); returns 'completed', 'exit' (EXIT) or 'stop'."""
        routine = self.find_routine_py(entry)
        if routine is None or routine.kind != "PROC":
            raise RapidRuntimeError(f"no PROC {entry} in module(s) {', '.join(self.module_names)}")
        return self._top(lambda: self.call_routine(routine, [], []))[0]

    def call(self, name: str, *args: Any, **options: Any) -> Any:
        """Call a routine (PROC/FUNC/TRAP or builtin) from Python; a :class:`Ref` argument is passed by reference."""
        return self._top(lambda: self.call_from_python(name, args, options))[1]

    def get(self, name: str) -> Any:
        """A copy of module data ``name`` (num -> float, records -> Record, arrays -> list); LOCAL data as
        ``"Module:name"``, or by its bare name when one module only declares it."""
        return copy_value(self._global_ref(name).get())

    def set(self, name: str, value: Any) -> None:
        """Assign module data ``name`` (aggregates as lists, records as Record); CONSTs refuse."""
        ref = self._global_ref(name)
        try:
            ref.set(value)
        except ByteRangeError as e:
            raise RapidRuntimeError(str(e)) from None
        except TypeError as e:
            raise RapidRuntimeError(f"cannot set {name}: {e}") from None

    def ref(self, name: str) -> Ref:
        """A live reference to module data (pass to :meth:`call` for INOUT/VAR parameters)."""
        return self._global_ref(name)

    # ---- loading --------------------------------------------------------------------------------------
    def _load(self, modules: list[Tree]) -> None:
        self._check_names(modules)
        if self.options is not None:
            own = set().union(*(declared_names(m) for m in modules)) if modules else set()
            for module in modules:
                missing = missing_options(module, self.options, own)
                if missing:
                    tok, opts = missing[0]
                    need = " or ".join(str(o) for o in opts)
                    more = f" ({len(missing) - 1} more such name(s) in this module)" if len(missing) > 1 else ""
                    raise RapidLoadError(
                        f"{tok} needs RobotWare option {need}, which is not installed{more}",
                        module=str(module.children[0]),
                        line=tok.line,
                        name=str(tok),
                        options=tuple(str(o) for o in opts),
                    )
        frame = Frame(None)
        self._stack = [frame]
        try:
            for module in modules:
                mod = str(module.children[0]).lower()
                frame.module = mod
                self.module_names.append(str(module.children[0]))
                self.local_data.setdefault(mod, {})
                self.local_routines.setdefault(mod, {})
                for item in module.children[2:]:
                    if item.data == "record_decl":
                        try:
                            define_record(item.children[0], [(f.children[1], f.children[0]) for f in item.children[1:]])
                        except ValueError as e:
                            raise RapidRuntimeError(str(e), line=item.meta.line) from None
                    elif item.data == "data_decl":
                        frame.line = item.meta.line
                        local = _is_local(item)
                        self.declare(item, frame, self.local_data[mod] if local else self.globals)
                        if not local:
                            self._owner[item.children[3].lower()] = mod
                    else:
                        routine = Routine.from_tree(item, mod)
                        table = self.local_routines[mod] if routine.local else self.routines
                        table[routine.key] = routine
                        if not routine.local:
                            self._owner[routine.key] = mod
        except RapidError as e:
            raise RapidRuntimeError(f"error initialising module data: {e}", errno=e.errno, line=frame.line) from None
        finally:
            self._stack = []

    def _check_names(self, modules: list[Tree]) -> None:
        """A name declared twice where it is visible (globals: the task; LOCAL: the module) is ambiguous."""
        seen: dict[str, tuple[str, int]] = {}  # global name -> (module, line)
        for module in modules:
            mod = str(module.children[0])
            local_seen: dict[str, int] = {}
            for item in module.children[2:]:
                if item.data == "record_decl":
                    continue
                name = item.children[3] if item.data == "data_decl" else item.children[2 if item.data == "func" else 1]
                key, line = name.lower(), item.meta.line
                if _is_local(item):
                    if key in local_seen:
                        raise RapidLoadError(
                            f"ambiguous name {name}: declared twice in module {mod} (lines {local_seen[key]} and "
                            f"{line})",
                            module=mod,
                            line=line,
                            name=str(name),
                        )
                    local_seen[key] = line
                    continue
                if key in seen:
                    other, other_line = seen[key]
                    where = (
                        f"twice in module {mod} (lines {other_line} and {line})"
                        if other == mod
                        else (f"in modules {other} (line {other_line}) and {mod} (line {line})")
                    )
                    raise RapidLoadError(
                        f"ambiguous name {name}: declared {where}", module=mod, line=line, name=str(name)
                    )
                seen[key] = (mod, line)

    def declare(self, decl: Tree, frame: Frame, scope: dict[str, Any]) -> None:
        """Create the variable of a ``data_decl`` (default value, then the initialiser if any) in ``scope``."""
        _, storage, type_name, name, dims, init = decl.children
        shape = [self._dim(self.eval(e, frame)) for e in dims.children] if dims is not None else None
        value = default_value(type_name, shape)
        if init is not None:
            try:
                value = assign_like(value, self.eval(init, frame), type_name.lower() == "dnum")
                check_range(type_name.lower(), value, str(name))
            except ByteRangeError as e:
                raise self.fault(str(e)) from None
            except TypeError as e:
                raise self.fault(f"initialiser of {name}: {e}") from None
        scope[name.lower()] = Ref(Cell(str(name), value, storage.children[0].upper(), str(type_name)))

    def _dim(self, v: Any) -> int:
        if not isinstance(v, float) or not v.is_integer() or v < 1:
            raise self.fault(f"array dimension must be a positive integer, got {v!r}")
        return int(v)

    # ---- names ----------------------------------------------------------------------------------------
    def lookup(self, name: str, frame: Frame) -> Ref:
        """A name seen from ``frame``: its routine's data, its module's LOCAL data, the task's, system data."""
        if name in frame.vars:
            ref = frame.vars[name]
            if ref is None:
                raise RapidError("ERR_NOTPRES", f"optional parameter {name} was not given")
            return ref
        local = self.local_data.get(frame.module)
        ref = (local and local.get(name)) or self.globals.get(name) or self.system.get(name)
        if ref is None:
            raise self.fault(f"undefined name {name}")
        return ref

    def find_routine(self, name: str, module: str) -> Routine | None:
        """The routine ``name`` as module ``module`` (lower case) sees it: its own LOCAL ones first."""
        key = name.lower()
        local = self.local_routines.get(module)
        return (local and local.get(key)) or self.routines.get(key)

    def find_routine_py(self, name: str) -> Routine | None:
        """A routine named from Python: global, ``"Module:name"``, or a LOCAL one only one module declares."""
        mod, key = _split_name(name)
        if mod is not None:
            local = self.local_routines.get(mod, {}).get(key)
            if local is not None:
                return local
            routine = self.routines.get(key)
            return routine if routine is not None and routine.module == mod else None
        return self.routines.get(key) or _unique(name, "routine", self.local_routines, self.module_names)

    def _global_ref(self, name: str) -> Ref:
        mod, key = _split_name(name)
        if mod is not None:
            ref = self.local_data.get(mod, {}).get(key)
            if ref is None and self._owner.get(key) == mod:
                ref = self.globals.get(key)
        else:
            ref = self.globals.get(key) or self.system.get(key)
            ref = ref or _unique(name, "data", self.local_data, self.module_names)
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
        except ByteRangeError as e:
            raise self.fault(str(e)) from None
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


def _is_local(item: Tree) -> bool:
    scope = item.children[0]
    return scope is not None and scope.children[0].upper() == "LOCAL"


def _split_name(name: str) -> tuple[str | None, str]:
    """``"Module:name"`` -> (module, name), lower case; a bare name -> (None, name)."""
    mod, sep, key = name.rpartition(":")
    return (mod.strip().lower() if sep else None), key.strip().lower()


def _unique(name: str, what: str, tables: dict[str, dict[str, Any]], modules: list[str]) -> Any:
    """The LOCAL ``name`` if exactly one module declares it; several: ambiguous (name the module)."""
    key = name.lower()
    found = [(mod, table[key]) for mod, table in tables.items() if key in table]
    if len(found) > 1:
        names = {m.lower(): m for m in modules}
        where = ", ".join(names.get(m, m) for m, _ in found)
        raise RapidRuntimeError(
            f"{what} {name} is LOCAL in modules {where}: say which, e.g. '{names.get(found[0][0], found[0][0])}:{name}'"
        )
    return found[0][1] if found else None
