"""What the operator does at the emulated IRC5, and what the controller does about it: the task model (Stop,
Start, PP to main, emergency stop, motors off, the enabling device) and the event log. Mixed into
:class:`~.controller.ControllerEmulator`. See docs/emulator.md, "The task model".
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from maniskill_irb120.abb.emulator.rapid import Interpreter
    from maniskill_irb120.abb.emulator.robot import EmulatedIRB120


@dataclass(frozen=True)
class Event:
    """One event-log entry."""

    # the IRC5 event number where known: 10010 Motors OFF, 10011 Motors ON, 10013 Emergency stop, 50024, 80001-80003
    # (ErrWrite), from integrators' logs and issue threads (the event-log manual was not at hand: verify)
    code: int | None
    title: str
    detail: str = ""
    time: float = 0.0  # time.monotonic() when it was logged


class ControllerStateError(RuntimeError):
    """The operator asked for something the controller does not do in its present state (it says why)."""


class Pendant:
    """The operator's controls and the program's state, mixed into :class:`ControllerEmulator` (which provides
    ``robot``, ``interp``, ``signals``, ``op_mode`` and calls :meth:`_init_pendant`).

    An emergency stop, motors off (a guard stop, or the enabling device released in manual mode) and Stop all halt
    the program where it stands and stop the robot on its path; the program sends nothing more (docs/reference.md,
    "IRC5 / RAPID behaviour"). Start needs the motors on: in manual mode while the enabling device is held, in
    automatic mode after the Motors On button (ABB Operating manual IRC5)."""

    robot: EmulatedIRB120
    interp: Interpreter
    signals: dict[str, int]
    op_mode: str
    error: BaseException | None
    ended: bool

    def _init_pendant(self) -> None:
        self.event_log: list[Event] = []
        self.at_main = False  # PP was moved to main: Start runs the entry routine from the top
        self._path_was_stopped = False

    def log_event(self, code: int | None, title: str, detail: str = "") -> None:
        self.event_log.append(Event(code, title, detail, time.monotonic()))

    def events(self, code: int | None = None) -> list[Event]:
        """The event log (program, operator and motion events, oldest first); only ``code``'s with a code."""
        merged = self.event_log + [Event(*e) for e in self.robot.events]
        merged.sort(key=lambda e: e.time)
        return [e for e in merged if code is None or e.code == code]

    # ------------------------------------------------------------------ the program's state
    @property
    def program_state(self) -> str:
        """``running``; ``stopped`` (Start goes on, or PP to main first); ``ended`` (a fatal error or the
        program returned: PP to main, then Start)."""
        if self.ended or not self.thread.is_alive():  # type: ignore[attr-defined]
            return "ended"
        return "stopped" if self.interp.is_halted or self.at_main else "running"

    @property
    def motors_on(self) -> bool:
        return bool(self.signals["doMotorsOn"])

    @property
    def emergency_stop_active(self) -> bool:
        return bool(self.signals["doEmergencyStop"])

    def _halt(self, quick: bool) -> None:
        """The program stops where it stands and the robot stops on its path."""
        if not self.interp.is_halted:
            self._path_was_stopped = self.robot.stopped  # the program's own StopMove stays in force at Start
        self.interp.halt()
        self.robot.stop(quick=quick)

    # ------------------------------------------------------------------ operator controls
    def press_stop(self) -> None:
        """The pendant's Stop button: the program halts, the robot stops on its path; Start goes on."""
        if self.program_state == "running":
            self._halt(quick=False)
            self.log_event(None, "Program stopped", "Stop button")

    def emergency_stop(self) -> None:
        """An emergency stop: motors off, the program halts and the robot stops at once."""
        self.signals.update(doEmergencyStop=1, doMotorsOn=0)
        self._halt(quick=True)
        self.log_event(10013, "Emergency stop state")

    def reset_emergency_stop(self) -> None:
        """The e-stop button released and reset: the motors stay off until switched on again."""
        if self.emergency_stop_active:
            self.signals["doEmergencyStop"] = 0
            self.log_event(10010, "Motors OFF state", "emergency stop reset")

    def enabling_device(self, held: bool) -> None:
        """Manual modes: holding the enabling device turns the motors on; releasing it turns them off and halts
        the program (it does not go on by itself when the device is held again: press Start)."""
        if self.op_mode == "auto":
            raise ControllerStateError("the enabling device works in the manual modes only (the key is at auto)")
        if held:
            self._motors(True, "enabling device held")
        else:
            self.signals["doMotorsOn"] = 0
            self._halt(quick=True)
            self.log_event(10010, "Motors OFF state", "enabling device released")

    def motors_on_button(self) -> None:
        """Automatic mode: the Motors On button."""
        if self.op_mode != "auto":
            raise ControllerStateError("in the manual modes the motors come on with the enabling device")
        self._motors(True, "Motors On button")

    def _motors(self, on: bool, why: str) -> None:
        if on and self.emergency_stop_active:
            raise ControllerStateError("emergency stop active: release and reset it first")
        if on and not self.motors_on:
            self.signals["doMotorsOn"] = 1
            self.log_event(10011, "Motors ON state", why)

    def motors_off_fault(self, why: str) -> None:
        """Motors off while the program runs (a guard stop; in manual mode the enabling device let go)."""
        if self.op_mode == "auto":
            self.signals["doMotorsOn"] = 0
            self._halt(quick=True)
            self.log_event(10010, "Motors OFF state", why)
        else:
            self.enabling_device(False)

    def pp_to_main(self) -> None:
        """Move the program pointer to main (the program must be stopped): UNDO handlers run, the path is
        cleared, and Start runs the entry routine from the top."""
        state = self.program_state
        if state == "running":
            raise ControllerStateError("stop the program before moving the program pointer to main")
        self.at_main = True
        if state == "stopped" and self.interp.is_halted:
            self.interp.pp_to_main()  # the task's thread unwinds, then waits for Start
        # the path is cleared and the stop that held it (the halt's, or the program's own StopMove) is over: the
        # program started from main moves the robot again. An IRC5 starts a program from main with a fresh path
        # and no StopMove in force (docs/rapid_subset.md, "Controller behaviour the emulator models"; verify).
        self.robot.clear_path()
        self.robot.start()
        self._path_was_stopped = False
        self.log_event(None, "PP to main")

    def press_start(self) -> None:
        """The pendant's Start button: the program goes on where it stood (the robot first finishes its queued
        path; RESTART event routines run), or from the top after PP to main (START event routines run)."""
        if self.emergency_stop_active:
            raise ControllerStateError("emergency stop active: release and reset it, then turn the motors on")
        if not self.motors_on:
            how = "hold the enabling device" if self.op_mode != "auto" else "press Motors On"
            raise ControllerStateError(f"motors are off: {how}, then Start")
        state = self.program_state
        if state == "running":
            return
        if state == "ended" and not self.at_main:
            raise ControllerStateError(f"the program has ended ({self.error or 'returned'}): PP to main, then Start")
        self.log_event(None, "Program started", "from main" if self.at_main else "resumed")
        self._start_program()  # type: ignore[attr-defined]
