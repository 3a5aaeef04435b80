"""Program execution as a controller's task runs it: stopped and started from outside (:meth:`halt`,
:meth:`resume`), the program pointer moved to main (:meth:`pp_to_main`, UNDO handlers run), and every statement
costing controller time (``statement_cost_s``, an estimate; 0 disables it).
See docs/rapid_subset.md, "Execution control", and docs/emulator.md, "The task model".
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from maniskill_irb120.abb.emulator.rapid.errors import RapidStopped


class PPToMain(Exception):
    """The program pointer was moved to main: unwinds every routine (their UNDO handlers run on the way)."""


class ExecutionMixin:
    """Stop/start, PP to main and statement pacing for :class:`~.interpreter.Interpreter` (which calls
    :meth:`_init_execution` and routes ``tick``/``check_stop`` here)."""

    statements: int
    max_statements: int | None

    def _init_execution(self, statement_cost_s: float) -> None:
        if not statement_cost_s >= 0:
            raise ValueError(f"statement_cost_s={statement_cost_s!r}: a time >= 0 s per statement")
        self.statement_cost_s = statement_cost_s
        self._stop = threading.Event()
        self._running = threading.Event()  # cleared by halt(): the program waits at its next check
        self._running.set()
        self._pp_main = False
        self._restart_pending = False
        self.restart_routines: list[str] = []  # RESTART event routines, run when a halted program resumes
        self.halted = threading.Event()  # set while the program actually stands still (after halt())
        # called wherever the program may be stopped: raises what stops the program from outside it (the
        # controller's motion supervision: an error the robot met while moving stops the program at once)
        self.supervision: Callable[[], None] | None = None
        self._owed_s = 0.0  # controller time of statements not yet paid for
        self._cpu_mark = (threading.get_ident(), time.thread_time())  # CPU time is per thread

    # ---- from outside (thread-safe) -------------------------------------------------------------------------
    def request_stop(self) -> None:
        """The program raises :class:`RapidStopped` before its next statement/wait (the emulator shuts down)."""
        self._stop.set()
        self._running.set()

    @property
    def stop_event(self) -> threading.Event:
        """Set by request_stop(); blocking builtins should wait on it (as WaitTime does)."""
        return self._stop

    def halt(self) -> None:
        """The program stops before its next statement, or where a blocking instruction polls."""
        self._running.clear()

    def resume(self) -> None:
        """A halted program goes on where it stood, inside the instruction that was running (a read resumes its
        wait), after the RESTART event routines: the controller resumes the program pointer where it stood (ABB
        Operating manual IRC5, "Starting programs"; docs/reference.md "Start without PP to main resumes")."""
        if not self._running.is_set():
            self._restart_pending = True
        self._running.set()

    def pp_to_main(self) -> None:
        """Move the program pointer to main: a halted program unwinds, innermost routine first, running each
        one's UNDO handler (RAPID's UNDO: "executed when the program pointer is moved out of the routine"), and ends
        its run()."""
        self._pp_main = True
        self._running.set()

    @property
    def is_halted(self) -> bool:
        return not self._running.is_set()

    # ---- from the program's thread ---------------------------------------------------------------------------
    def check_stop(self) -> None:
        """Where the program may be stopped: between statements and inside blocking instructions."""
        if not self._running.is_set():
            self.halted.set()
            self._running.wait()
            self.halted.clear()
            self._pay(0.0)  # standing still is not statement time
        if self._stop.is_set():
            self._stop.clear()
            raise RapidStopped("stop requested")
        if self._pp_main:
            self._pp_main = False
            self._restart_pending = False
            raise PPToMain()
        if self.supervision is not None:
            self.supervision()
        if self._restart_pending:
            self._restart_pending = False
            for name in self.restart_routines:
                self.call(name)  # type: ignore[attr-defined]

    def tick(self) -> None:
        """Before every statement: stop/start, the statement budget and the statement's controller time."""
        self.check_stop()
        self.statements += 1
        if self.max_statements is not None and self.statements > self.max_statements:
            raise RapidStopped(f"statement budget of {self.max_statements} exhausted")
        if self.statement_cost_s:
            self._owed_s += self.statement_cost_s
            if self._owed_s >= 0.001:  # pay in whole milliseconds: sleep() is no finer than that
                self._pay(self._owed_s)

    def settle_time(self) -> None:
        """A blocking instruction starts: the statements before it are paid for first (and its wait is not
        statement time)."""
        self._pay(self._owed_s)

    def _pay(self, owed: float) -> None:
        """Sleep what ``owed`` exceeds the CPU time this thread spent since the last payment."""
        thread, mark = self._cpu_mark
        now = time.thread_time()
        if owed > 0 and thread == threading.get_ident() and owed > now - mark:
            time.sleep(owed - (now - mark))
            now = time.thread_time()
        self._owed_s, self._cpu_mark = 0.0, (threading.get_ident(), now)
