"""What the parts of the interpreter need from each other: the :class:`Runtime` protocol. The
:class:`~.interpreter.Interpreter` is assembled from mixins (:mod:`.expressions`, :mod:`.statements`, :mod:`.calls`),
each typing ``self`` as a :class:`Runtime`, so a part reads against this protocol only. See docs/rapid_subset.md.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol, runtime_checkable

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.errors import RapidRuntimeError
from maniskill_irb120.abb.emulator.rapid.frames import Frame, Routine
from maniskill_irb120.abb.emulator.rapid.registry import Builtin, Builtins
from maniskill_irb120.abb.emulator.rapid.values import Cell, Ref

Args = list[Any]  # positional argument sources (TreeArg / ValueArg in .calls): .value() and .ref(what)
Options = list[tuple[str, Any]]  # (option name, argument source, or None for a switch)


class Clock(Protocol):
    """Time for WaitTime/WaitUntil/ClkRead (:class:`~.stdlib.SystemClock`, :class:`~.stdlib.ManualClock`)."""

    def now(self) -> float: ...

    def sleep(self, seconds: float, stop: threading.Event) -> None: ...


@runtime_checkable
class Runtime(Protocol):
    """The interpreter as its parts see it (implemented by :class:`~.interpreter.Interpreter`).

    * :mod:`.expressions` (``eval``, ``condition``, ``resolve``) needs ``lookup``, ``fault``, ``call_function``;
    * :mod:`.statements` (``execute``, ``block``, ``wait_until``) needs expressions, ``call_statement``, ``store``,
      ``tick``, ``check_stop``, ``clock``, ``max_retries``, ``_errno``, ``connections``;
    * :mod:`.calls` (``call_*``) needs expressions, ``block``, ``wait_until``, ``declare``, ``find_routine``,
      ``find_routine_py``, ``builtins``, ``_stack``;
    * :mod:`.interpreter` provides the state, names (``lookup``, ``find_routine``, ``store``, ``declare``,
      ``fault``) and ``tick``. Names resolve as a task does: the frame's variables, then its module's LOCAL
      names (``Frame.module``), then the task's global names, then system data."""

    # ---- state (interpreter.py) ----
    builtins: Builtins
    routines: dict[str, Routine]  # global (task-wide) routines
    local_routines: dict[str, dict[str, Routine]]  # module (lower case) -> its LOCAL routines
    clock: Clock
    max_retries: int  # RETRYs of one statement before its error goes to the caller
    connections: dict[int, str]  # CONNECT intno WITH trap, keyed by id(cell)
    err_log: list[str]  # ErrWrite entries (and failed UNDO handlers)
    _stack: list[Frame]  # active routine frames (the last one locates faults)
    _errno: Cell  # the ERRNO system variable

    @property
    def stop_event(self) -> threading.Event: ...

    # ---- names and errors (interpreter.py) ----
    def lookup(self, name: str, frame: Frame) -> Ref: ...

    def find_routine(self, name: str, module: str) -> Routine | None:
        """``name`` as seen from ``module`` (lower case): its LOCAL routines first, then the task's."""
        ...

    def find_routine_py(self, name: str) -> Routine | None:
        """A routine named from Python: global, ``"Module:name"``, or a LOCAL one only one module declares."""
        ...

    def store(self, ref: Ref, value: Any) -> None: ...

    def declare(self, decl: Tree, frame: Frame, scope: dict[str, Any]) -> None: ...

    def fault(self, message: str) -> RapidRuntimeError:
        """A fatal error at the current statement; callers ``raise rt.fault(...)``."""
        ...

    def tick(self) -> None:
        """Before every statement: honours request_stop() and the statement budget."""
        ...

    def check_stop(self) -> None: ...

    # ---- expressions.py ----
    def eval(self, t: Tree, frame: Frame) -> Any: ...

    def condition(self, t: Tree, frame: Frame) -> bool: ...

    def resolve(self, t: Tree, frame: Frame) -> Ref: ...

    # ---- statements.py ----
    def execute(self, st: Tree, frame: Frame) -> None: ...

    def block(self, stmts: Tree | None, frame: Frame) -> None: ...

    def wait_until(self, positional: Args, options: Options) -> None: ...

    # ---- calls.py ----
    def call_statement(self, st: Tree, frame: Frame) -> None: ...

    def call_function(self, t: Tree, frame: Frame) -> Any: ...

    def call_routine(self, routine: Routine, positional: Args, options: Options) -> Any: ...

    def call_builtin(self, b: Builtin, positional: Args, options: Options) -> Any: ...

    def call_from_python(self, name: str, args: tuple, options: dict[str, Any]) -> Any: ...
