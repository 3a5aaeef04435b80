"""Statements and ERROR-handler recovery (a mixin typed against :class:`~.contract.Runtime`). A
:class:`RapidError` raised by a routine's innermost statement runs that routine's ERROR handler at the point of
failure with ERRNO set (RETRY, TRYNEXT, RETURN, RAISE; the end of the handler is an implicit RAISE); one that leaves
the entry routine becomes :class:`RapidRuntimeError`. See docs/rapid_subset.md, "Errors and recovery".
"""

from __future__ import annotations

from lark import Tree

from maniskill_irb120.abb.emulator.rapid.contract import Args, Options, Runtime
from maniskill_irb120.abb.emulator.rapid.errors import ProgramHalt, RapidError
from maniskill_irb120.abb.emulator.rapid.expressions import compare
from maniskill_irb120.abb.emulator.rapid.frames import Frame, Propagate, Retry, Return, Routine, TryNext
from maniskill_irb120.abb.emulator.rapid.values import Cell, Ref, copy_value


class StatementsMixin:
    """``execute(statement, frame)`` with RAPID's error recovery; one ``_s_<rule>`` method per statement kind."""

    def block(self: Runtime, stmts: Tree | None, frame: Frame) -> None:
        if stmts is not None:
            for st in stmts.children:
                self.execute(st, frame)

    def execute(self: Runtime, st: Tree, frame: Frame) -> None:
        """Run one statement; a RapidError from it enters the routine's ERROR handler (RETRY/TRYNEXT here)."""
        retries = 0
        while True:
            frame.line = st.meta.line
            self.tick()
            try:
                getattr(self, "_s_" + st.data)(st, frame)
                return
            except RapidError as err:
                if err.line is None:
                    err.routine, err.line = frame.name, frame.line
                routine = frame.routine
                if frame.in_handler or routine is None or routine.handler is None or not _handles(self, routine, err):
                    raise
                if _run_handler(self, frame, err) == "trynext":
                    return
                retries += 1
                if retries > self.max_retries:
                    raise Propagate(err) from None

    def wait_until(self: Runtime, positional: Args, options: Options) -> None:
        """``WaitUntil [\\InPos,] cond [\\MaxTime:=s] [\\TimeFlag:=flag] [\\PollRate:=s]``, polling the condition."""
        if len(positional) != 1:
            raise self.fault("WaitUntil takes one condition")
        opts = {name.lower(): arg for name, arg in options}
        max_time = opts["maxtime"].value() if opts.get("maxtime") else None
        poll = opts["pollrate"].value() if opts.get("pollrate") else 0.1
        flag = opts["timeflag"].ref("\\TimeFlag") if opts.get("timeflag") else None
        if flag is not None:
            self.store(flag, False)
        start = self.clock.now()
        while not self.condition(positional[0].tree, positional[0].frame):
            if max_time is not None and self.clock.now() - start >= max_time:
                if flag is None:
                    raise RapidError("ERR_WAIT_MAXTIME", f"WaitUntil: condition still false after {max_time} s")
                self.store(flag, True)
                return
            self.clock.sleep(poll, self.stop_event)
            self.check_stop()

    def _s_assign(self: Runtime, st: Tree, frame: Frame) -> None:
        target, expr = st.children
        self.store(self.resolve(target, frame), self.eval(expr, frame))

    def _s_proc_call(self: Runtime, st: Tree, frame: Frame) -> None:
        self.call_statement(st, frame)

    def _s_if_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        cond, body, *rest = st.children
        if self.condition(cond, frame):
            return self.block(body, frame)
        for part in rest:
            if part is None:
                continue
            if part.data == "elseif":
                if self.condition(part.children[0], frame):
                    return self.block(part.children[1], frame)
            else:
                return self.block(part.children[0], frame)

    def _s_compact_if(self: Runtime, st: Tree, frame: Frame) -> None:
        if self.condition(st.children[0], frame):
            self.execute(st.children[1], frame)

    def _s_while_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        while self.condition(st.children[0], frame):
            self.block(st.children[1], frame)
            frame.line = st.meta.line

    def _s_for_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        name, start, stop, step, body = st.children
        a, b = self.eval(start, frame), self.eval(stop, frame)
        s = self.eval(step, frame) if step is not None else 0.0
        if not all(isinstance(v, float) for v in (a, b, s)) or (step is not None and s == 0):
            raise self.fault("FOR needs num FROM/TO values and a non-zero STEP")
        if step is None:  # without STEP, RAPID counts towards TO in steps of 1
            s = 1.0 if a <= b else -1.0
        key, cell = name.lower(), Cell(str(name), a, "FOR")
        saved = frame.vars.get(key, _MISSING)
        frame.vars[key] = Ref(cell)
        try:
            while (cell.value <= b) if s > 0 else (cell.value >= b):
                self.block(body, frame)
                cell.value += s
        finally:
            if saved is _MISSING:
                del frame.vars[key]
            else:
                frame.vars[key] = saved

    def _s_test_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        value, *cases = st.children
        v = self.eval(value, frame)
        for case in cases:
            if case is None:
                continue
            if case.data == "test_default":
                return self.block(case.children[0], frame)
            if any(compare(self, v, "=", self.eval(e, frame)) for e in case.children[:-1]):
                return self.block(case.children[-1], frame)

    def _s_return_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        expr = st.children[0]
        raise Return(copy_value(self.eval(expr, frame)) if expr is not None else None)

    def _s_raise_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        expr = st.children[0]
        if expr is None:
            if not frame.in_handler:
                raise self.fault("RAISE without an error number is only allowed in an ERROR handler")
            raise Propagate(frame.error)
        errno = self.eval(expr, frame)
        if not isinstance(errno, float) or not errno.is_integer():
            raise self.fault(f"RAISE needs an integer errnum, got {errno!r}")
        err = RapidError(int(errno), "raised by RAISE")
        err.routine, err.line = frame.name, frame.line
        raise Propagate(err) if frame.in_handler else err

    def _s_retry_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        if not frame.in_handler:
            raise self.fault("RETRY outside an ERROR handler")
        raise Retry()

    def _s_trynext_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        if not frame.in_handler:
            raise self.fault("TRYNEXT outside an ERROR handler")
        raise TryNext()

    def _s_exit_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        raise ProgramHalt("exit")

    def _s_connect_stmt(self: Runtime, st: Tree, frame: Frame) -> None:
        ref = self.resolve(st.children[0], frame)
        self.connections[id(ref.cell)] = str(st.children[1])


def _handles(rt: Runtime, routine: Routine, err: RapidError) -> bool:
    if routine.handler_filter is None:
        return True
    seen_from = Frame(None, module=routine.module)
    return any(rt.lookup(n.lower(), seen_from).get() == err.errno for n in routine.handler_filter)


def _run_handler(rt: Runtime, frame: Frame, err: RapidError) -> str:
    frame.in_handler, frame.error = True, err
    rt._errno.value = float(err.errno)
    line = frame.line
    try:
        rt.block(frame.routine.handler, frame)
    except Retry:
        return "retry"
    except TryNext:
        return "trynext"
    except RapidError as inner:  # an error inside the handler goes to the caller
        raise Propagate(inner) from None
    finally:
        frame.in_handler, frame.error, frame.line = False, None, line
    raise Propagate(err)  # end of handler reached: implicit RAISE


_MISSING = object()
