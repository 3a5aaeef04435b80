"""Robot Web Services 1.0 on the controller emulator: the subset a deployment uses, so that ``maniskill-irb120
deploy`` (``abb-robot-client`` underneath) is tested against the checks a RobotWare 6 IRC5 makes (mastership, RMMP,
sessions, the file service, load-time checks). Binds 127.0.0.1 only. What is served and refused: docs/emulator.md,
"Robot Web Services"; each resource with its source: docs/real_robot.md, "What was verified on the emulator only".

    maniskill-irb120 emulator --rws 127.0.0.1:0 --options 616-1,608-1   # first line printed: the RWS URL
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path, PurePosixPath
from urllib.parse import parse_qs, unquote, urlsplit

from maniskill_irb120.abb.emulator.controller import STATEMENT_COST_US, STOCK_MAIN_MODULE, ControllerEmulator
from maniskill_irb120.abb.emulator.pendant import ControllerStateError
from maniskill_irb120.abb.emulator.rapid import OPTIONS, RapidRuntimeError, RapidSyntaxError, parse, parse_options
from maniskill_irb120.abb.emulator.rapid.values import ClockVar, Opaque, RawBytes, copy_value, format_value

REALM = "validusers@robapi.abb"  # RobotWare 6's digest realm (integrator knowledge, verify)
DEFAULT_USER = "Default User"  # ABB's default user and password, as abb-robot-client defaults to them
DEFAULT_PASSWORD = "robotics"
ROBOTWARE_VERSION = "6.15.04.00"  # the RobotWare 6 the emulator claims to be (any RobotWare 6 serves RWS 1.0)
TASK = "T_ROB1"
HOME = "$HOME"
OPMODES = {"manual_reduced": "MANR", "manual_full": "MANF", "auto": "AUTO"}  # RWS's names (abb-robot-client)
CHANNEL_MODULE_NAMES = {"irb120socket": "tcp", "irb120serial": "serial"}  # the loaded channel module -> the link
ZONE_MODULE = "irb120zone"  # loaded: its POWER ON event routine runs before the program starts
MAX_BODY = 1 << 20  # a module file is a few tens of kB; anything bigger is refused
MAX_NONCES = 64
# Sessions. abb-robot-client answers an HTTP 503 with "too many active connections": RobotWare 6 keeps a bounded
# number of sessions and drops one nobody uses. 70 is the number integrators quote for RobotWare 6 and 15 minutes
# of inactivity the lifetime assumed here; neither is in a public ABB source at hand (verify both).
MAX_SESSIONS = 70
SESSION_IDLE_S = 900.0
# RMMP (Request Manual Mode Privileges; RWS 1.0 reference, "Operations on RMMP"): a request nobody answers within
# 10 s of the client's last poll is deleted. The emulated operator answers after OPERATOR_DELAY_S.
RMMP_TIMEOUT_S = 10.0
OPERATOR_DELAY_S = 0.2
OPERATORS = ("grant", "deny", "absent")
# RWS 1.0 reference, "RobotWare return codes service": setting RAPID data without mastership is answered 400 Bad
# Request with this controller code. The emulator gives it to every write refused for want of mastership (verify
# for loadmod, unloadmod and the program pointer).
CODE_NO_MASTERSHIP = -1073414146
# The poll's "no such request" code, from the same reference's "Poll for RMMP grant status" example.
CODE_NO_RMMP_REQUEST = -1073445870


class RWSError(Exception):
    """An RWS error answer: the HTTP status, the message and the controller's code (the body's
    ``_embedded.status``); without a known controller code the emulator sends ``-status`` (verify)."""

    def __init__(self, status: int, msg: str, code: int | None = None):
        self.status, self.msg = status, msg
        self.code = -status if code is None else code
        super().__init__(f"{status}: {msg}")


@dataclass
class Rmmp:
    """One session's RMMP request or grant: ``state`` pending or granted; ``polled`` the client's last poll
    (time.monotonic()); ``answer_at`` when the emulated operator answers a pending request."""

    session: str
    uid: int
    privilege: str  # modify or exec
    state: str
    polled: float
    answer_at: float | None


@dataclass
class LoadedModule:
    name: str  # as the module declares it
    text: str
    path: str | None  # the file it was loaded from ($HOME/...); None for the stock MainModule
    sysmod: bool


@dataclass
class LogEntry:
    msgtype: int  # 1 information, 2 warning, 3 error (abb-robot-client's EventLogEntry)
    code: int
    title: str
    desc: str
    time: float  # time.monotonic(), as the program's own events


def _msgtype(code: int | None, title: str) -> int:
    if code == 80001 or "error" in title.lower() or code == 10013:
        return 3
    if code in (80002, 50024):
        return 2
    return 1


def _entries(emu: ControllerEmulator | None) -> list[LogEntry]:
    """A task's own events (pendant, motion, ErrWrite) as log entries; code 0 where no event number is known."""
    if emu is None:
        return []
    return [LogEntry(_msgtype(e.code, e.title), e.code or 0, e.title, e.detail, e.time) for e in emu.events()]


class VirtualController:
    """The controller behind the web services: its options, key switch, file system ($HOME in a temporary folder),
    task ``T_ROB1`` (the stock MainModule at first, program pointer at ``main``), motors, mastership and event log.
    Every method takes the lock: the HTTP server serves each client on its own thread.

    ``main_entry``: the task's main entry (what resetpp moves the program pointer to). ``op_mode``: the key switch
    (``manual_reduced``, ``manual_full``, ``auto``); settable. The running program, once started, is
    :attr:`program` (a :class:`ControllerEmulator`) and the PC connects to :attr:`program_url`.

    ``operator``: the person at the FlexPendant who answers a remote client's RMMP request in the manual modes:
    ``grant`` (after about :data:`OPERATOR_DELAY_S`), ``deny`` (likewise) or ``absent`` (never; the request
    lapses). :meth:`answer_rmmp` answers by hand."""

    def __init__(
        self,
        options: tuple[str, ...] | str = (),
        op_mode: str = "manual_reduced",
        main_entry: str = "main",
        statement_cost_us: float = STATEMENT_COST_US,
        system_name: str = "IRB120_emulator",
        operator: str = "grant",
    ):
        if operator not in OPERATORS:
            raise ValueError(f"operator={operator!r}: use one of {', '.join(OPERATORS)}")
        self.operator = operator
        self.options = parse_options(options)
        self.op_mode = op_mode
        self.main_entry = main_entry
        self.statement_cost_us = statement_cost_us
        self.system_name = system_name
        self.lock = threading.RLock()
        self._tmp = tempfile.TemporaryDirectory(prefix="rws-home-")
        self.home = Path(self._tmp.name)
        self.modules: dict[str, LoadedModule] = {
            "mainmodule": LoadedModule("MainModule", STOCK_MAIN_MODULE, None, False)
        }
        self.pp: str | None = main_entry  # the routine the program pointer stands at (None: no program pointer)
        self.speed_ratio = 100
        self.motors_on = False
        self.master: str | None = None  # the session holding mastership
        self.rmmp: Rmmp | None = None  # the one RMMP request or grant (a pending request, or a held privilege)
        self._rmmp_outcome: dict[str, str] = {}  # session -> REJECTED, for the poll after a refusal
        self._uids: dict[str, int] = {}  # session -> its user id, as the pendant sees the requester
        self._next_uid = 10
        self.log: list[LogEntry] = []
        self.program: ControllerEmulator | None = None
        self.program_url: str | None = None
        self._replace_program(self._build())

    @property
    def op_mode(self) -> str:
        """The key switch; turning it reaches the running program (what its ``OpMode()`` reads)."""
        return self._op_mode

    @op_mode.setter
    def op_mode(self, mode: str) -> None:
        """Turning the key, as an IRC5 does it (operating manual IRC5, "Operating modes"; verify the details):
        a program that runs stops and the motors go off (finding 9); leaving AUTO for a manual mode takes
        mastership from the remote client (in manual the operator at the pendant is in charge; RWS 1.0 reference,
        mastership request: "In manual mode, mastership can be gained after getting RMMP"), and any change
        revokes RMMP, which exists only in the manual modes and for the mode it was granted in."""
        if mode not in OPMODES:
            raise ValueError(f"op_mode={mode!r}: use one of {sorted(OPMODES)}")
        old = getattr(self, "_op_mode", None)
        lock = getattr(self, "lock", None)
        if lock is None:  # __init__: nothing to revoke yet
            self._op_mode = mode
            return
        with lock:
            if old == mode:
                return
            program = self.program
            if program is not None and self.started and (program.program_state == "running" or program.motors_on):
                program.motors_off_fault(f"operating mode changed to {OPMODES[mode]}")
            self.motors_on = False
            self._op_mode = mode
            if program is not None:
                program.op_mode = mode
            if old == "auto" and mode != "auto":
                self.master = None
            if self.rmmp is not None:
                self._rmmp_outcome[self.rmmp.session] = "REJECTED"
            self.rmmp = None
            self.log_event(1, "Operating mode changed", f"{OPMODES.get(old, old)} -> {OPMODES[mode]}")

    # ------------------------------------------------------------------ the task
    def _build(self, modules: dict[str, LoadedModule] | None = None) -> ControllerEmulator:
        """The task as ``modules`` make it (the emulator's load-time checks run here; raises as they do)."""
        mods = self.modules if modules is None else modules
        channel = next((CHANNEL_MODULE_NAMES[k] for k in mods if k in CHANNEL_MODULE_NAMES), "serial")
        emu = ControllerEmulator(
            channel,
            options=self.options,
            zone=ZONE_MODULE in mods,
            modules=[m.text for m in mods.values()],
            entry=self.pp or self.main_entry,
            op_mode=self.op_mode,
            statement_cost_us=self.statement_cost_us,
        )
        return emu

    def _replace_program(self, emu: ControllerEmulator) -> None:
        """``emu`` is the task from now on; the old one's events stay in the log."""
        old = self.program
        if old is not None:
            if old.thread.is_alive():
                old.stop()
            self.log.extend(_entries(old))
        self.program, self.program_url = emu, None

    @property
    def started(self) -> bool:
        return self.program is not None and self.program_url is not None

    @property
    def exec_state(self) -> str:
        """``running`` or ``stopped`` (RWS's ``ctrlexecstate``)."""
        with self.lock:
            if self.started and self.program.program_state == "running":
                return "running"
            return "stopped"

    @property
    def ctrl_state(self) -> str:
        """RWS's ``ctrlstate``: ``motoron``, ``motoroff`` or ``emergencystop``."""
        with self.lock:
            if self.started:
                if self.program.emergency_stop_active:
                    return "emergencystop"
                return "motoron" if self.program.motors_on else "motoroff"
            return "motoron" if self.motors_on else "motoroff"

    def log_event(self, msgtype: int, title: str, desc: str = "", code: int = 0) -> None:
        with self.lock:
            self.log.append(LogEntry(msgtype, code, title, desc, time.monotonic()))

    def events(self) -> list[LogEntry]:
        """The event log, oldest first: the controller's own entries and every program's (pendant, motion,
        ErrWrite). Entries without a known event number carry code 0."""
        with self.lock:
            merged = self.log + _entries(self.program)
        merged.sort(key=lambda e: e.time)
        return merged

    def _need_master(self, session: str | None, what: str) -> None:
        """A write without mastership: 400 and the controller's code (RWS 1.0 reference, "RobotWare return codes
        service", the example of a RAPID variable set without mastership)."""
        if session is None or self.master != session:
            held = "held by another client" if self.master else "not held"
            raise RWSError(
                400,
                f"{what} needs mastership (POST /rw/mastership?action=request): mastership is {held}",
                CODE_NO_MASTERSHIP,
            )

    # ------------------------------------------------------------------ mastership, RMMP, sessions
    def request_mastership(self, session: str) -> None:
        """Mastership for ``session``. In AUTO a remote client just asks; in the manual modes only after the
        operator granted it RMMP (RWS 1.0 reference, mastership request: "In manual mode, mastership can be gained
        after getting RMMP"; PC SDK: no remote write access in manual unless the operator allows it on the
        FlexPendant). The refusal's status, 403, is one the reference lists for this request (verify)."""
        with self.lock:
            if self.master not in (None, session):
                raise RWSError(409, "mastership is held by another client")
            if self.op_mode != "auto":
                self._tick_rmmp()
                held = self.rmmp is not None and self.rmmp.session == session and self.rmmp.state == "granted"
                if not held:
                    raise RWSError(
                        403,
                        f"mastership in {OPMODES[self.op_mode]} needs RMMP: POST /users/rmmp with privilege=modify, "
                        "poll GET /users/rmmp/poll until the operator grants it on the FlexPendant, then request "
                        "mastership (or turn the key to AUTO)",
                    )
            self.master = session

    def release_mastership(self, session: str) -> None:
        with self.lock:
            if self.master == session:
                self.master = None

    def end_session(self, session: str) -> None:
        """A session ended (logout, or it lapsed): its mastership and its RMMP go with it."""
        with self.lock:
            if self.master == session:
                self.master = None
            if self.rmmp is not None and self.rmmp.session == session:
                self.rmmp = None
            self._rmmp_outcome.pop(session, None)
            self._uids.pop(session, None)

    def _uid(self, session: str) -> int:
        if session not in self._uids:
            self._next_uid += 1
            self._uids[session] = self._next_uid
        return self._uids[session]

    def _tick_rmmp(self) -> None:
        """The emulated operator answers a pending request once its time has come; a request nobody answered
        within RMMP_TIMEOUT_S of the client's last poll is deleted (RWS 1.0 reference, "Operations on RMMP")."""
        r, now = self.rmmp, time.monotonic()
        if r is None or r.state != "pending":
            return
        if r.answer_at is not None and now >= r.answer_at and r.answer_at <= r.polled + RMMP_TIMEOUT_S:
            if self.operator == "grant":
                r.state = "granted"
                self.log_event(1, "RMMP granted", f"{r.privilege} to user {r.uid}")
            else:
                self._reject_rmmp("denied by the operator")
        elif now > r.polled + RMMP_TIMEOUT_S:
            self._reject_rmmp(f"not answered within {RMMP_TIMEOUT_S:g} s of the last poll")

    def _reject_rmmp(self, why: str) -> None:
        r = self.rmmp
        self._rmmp_outcome[r.session] = "REJECTED"
        self.rmmp = None
        self.log_event(1, "RMMP rejected", f"user {r.uid}: {why}")

    def request_rmmp(self, session: str, privilege: str) -> None:
        """A remote client asks for manual-mode privileges (RWS 1.0 reference, "Request RMMP": 202 Accepted,
        400 on a bad privilege). In AUTO there is nothing to ask for (400, verify); while another client's
        request is pending or granted a second is refused (409, verify)."""
        with self.lock:
            if privilege not in ("modify", "exec"):
                raise RWSError(400, f"privilege={privilege!r}: modify or exec")
            if self.op_mode == "auto":
                raise RWSError(
                    400, "RMMP is for the manual modes (MANR, MANF); in AUTO request mastership directly (verify)"
                )
            self._tick_rmmp()
            if self.rmmp is not None and self.rmmp.session != session:
                raise RWSError(409, f"user {self.rmmp.uid} holds or awaits RMMP; try again when it is released")
            now = time.monotonic()
            answer_at = None if self.operator == "absent" else now + OPERATOR_DELAY_S
            self.rmmp = Rmmp(session, self._uid(session), privilege, "pending", now, answer_at)
            self._rmmp_outcome.pop(session, None)
            self.log_event(1, "RMMP requested", f"{privilege} by user {self.rmmp.uid}")

    def poll_rmmp(self, session: str) -> str:
        """PENDING, GRANTED, REJECTED, or NO SUCH REQUEST (the reference's example answer); a poll keeps a
        pending request alive (RWS 1.0 reference, "Poll for RMMP grant status")."""
        with self.lock:
            self._tick_rmmp()
            r = self.rmmp
            if r is not None and r.session == session:
                if r.state == "pending":
                    r.polled = time.monotonic()
                    return "PENDING"
                return "GRANTED"
            return self._rmmp_outcome.get(session, "NO SUCH REQUEST")

    def rmmp_state(self, session: str) -> dict:
        """What GET /users/rmmp shows: the user id and privilege of the request or grant (``none`` when there is
        none; ``pending modify`` while the operator has not answered)."""
        with self.lock:
            self._tick_rmmp()
            r = self.rmmp
            if r is None:
                return {"userid": "0", "privilege": "none", "rmmpheldbyme": "false"}
            privilege = f"pending {r.privilege}" if r.state == "pending" else r.privilege
            return {"userid": str(r.uid), "privilege": privilege, "rmmpheldbyme": str(r.session == session).lower()}

    def cancel_rmmp(self, session: str) -> None:
        """The client gives up its held or pending privilege (RWS 1.0 reference, "Cancel held or requested
        RMMP"); mastership gained under it in a manual mode goes too (verify)."""
        with self.lock:
            if self.rmmp is not None and self.rmmp.session == session:
                self.rmmp = None
                if self.op_mode != "auto" and self.master == session:
                    self.master = None

    def answer_rmmp(self, grant: bool) -> None:
        """The operator answers the pending request on the FlexPendant by hand (tests; ``operator="absent"``)."""
        with self.lock:
            self._tick_rmmp()
            if self.rmmp is None or self.rmmp.state != "pending":
                raise ControllerStateError("no RMMP request is pending")
            if grant:
                self.rmmp.state = "granted"
                self.log_event(1, "RMMP granted", f"{self.rmmp.privilege} to user {self.rmmp.uid}")
            else:
                self._reject_rmmp("denied by the operator")

    def _need_stopped(self, what: str) -> None:
        if self.exec_state == "running":
            raise RWSError(409, f"{what}: the program is running; stop it first (verify)")

    # ------------------------------------------------------------------ files
    def file_path(self, path: str) -> Path:
        """A controller path (``$HOME/dir/file``, or ``HOME:/dir/file`` as RAPID writes it) on this machine;
        anything outside $HOME, or ``..``, is refused."""
        p = path.strip()
        if p.upper().startswith("HOME:"):
            p = HOME + "/" + p[5:].lstrip("/")
        parts = PurePosixPath(p).parts
        if not parts or parts[0].upper() != HOME:
            raise RWSError(404, f"{path}: unknown file system location (the emulator serves {HOME} only)")
        if any(part in ("..", ".") for part in parts[1:]):
            raise RWSError(400, f"{path}: '..' and '.' are not allowed in a path")
        return self.home.joinpath(*parts[1:])

    # ------------------------------------------------------------------ RAPID
    def load_module(self, session: str | None, modulepath: str, replace: bool) -> str:
        with self.lock:
            self._need_master(session, "loading a module")
            self._need_stopped("loading a module")
            path = self.file_path(modulepath)
            if not path.is_file():
                raise RWSError(400, f"loadmod: no file {modulepath}")
            text = path.read_text(errors="replace")
            try:
                tree = parse(text)
            except RapidSyntaxError as e:
                self.log_event(3, "Syntax error", f"file {modulepath}: {str(e).splitlines()[0]}")
                raise RWSError(400, f"loadmod: the module in {modulepath} was not loaded: see the event log") from None
            if len(tree.children) != 1:
                self.log_event(3, "Module not loaded", f"file {modulepath}: a file holds exactly one MODULE")
                raise RWSError(400, f"loadmod: the module in {modulepath} was not loaded: see the event log")
            name = str(tree.children[0].children[0])
            key = name.lower()
            if key in self.modules and not replace:
                raise RWSError(409, f"loadmod: module {name} is already loaded in {TASK} (replace=true replaces it)")
            mods = dict(self.modules)
            mods[key] = LoadedModule(name, text, modulepath, path.suffix.lower() == ".sys")
            try:
                emu = self._build(mods)
            except (RapidSyntaxError, RapidRuntimeError) as e:  # a missing option, an ambiguous name, bad data
                self.log_event(3, "Module not loaded", f"file {modulepath}: {e}")
                raise RWSError(400, f"loadmod: the module in {modulepath} was not loaded: see the event log") from None
            _keep_persistents(self.program, emu, skip=key)
            self.modules = mods
            self.pp = None  # the program pointer is lost; resetpp or set-pp-routine sets it again (verify)
            self._replace_program(emu)
            self.log_event(1, "Module loaded", f"module {name} from {modulepath} into {TASK}")
            return name

    def unload_module(self, session: str | None, module: str) -> None:
        with self.lock:
            self._need_master(session, "unloading a module")
            self._need_stopped("unloading a module")
            key = module.strip().lower()
            if key not in self.modules:
                raise RWSError(400, f"unloadmod: no module {module} in {TASK}")
            mods = {k: v for k, v in self.modules.items() if k != key}
            emu = self._build(mods)
            _keep_persistents(self.program, emu, skip=key)
            self.modules = mods
            self.pp = None
            self._replace_program(emu)
            self.log_event(1, "Module unloaded", f"module {module} from {TASK}")

    def set_pp(self, session: str | None, routine: str | None) -> None:
        """PP to ``routine`` (None: to the task's main entry, resetpp)."""
        with self.lock:
            self._need_master(session, "moving the program pointer")
            self._need_stopped("moving the program pointer")
            target = routine or self.main_entry
            found = self.program.interp.find_routine_py(target)
            where = "set-pp-routine" if routine else f"resetpp (the task's main entry is {self.main_entry})"
            if found is None or found.kind != "PROC":
                raise RWSError(400, f"{where}: no PROC {target} in {TASK}")
            if found.params:  # nothing would pass its arguments: the FlexPendant's PP to Routine lists none such
                raise RWSError(
                    400,
                    f"{where}: PROC {target} takes parameters; the program pointer goes to a PROC without "
                    "parameters only (operating manual IRC5 with FlexPendant, PP to Routine; verify the answer)",
                )
            if self.started:
                try:
                    self.program.pp_to_main()  # UNDO handlers run, the path is cleared
                except ControllerStateError as e:
                    raise RWSError(409, str(e)) from None
            self.program.entry = target
            self.pp = target
            self.log_event(1, "Program pointer moved", f"{TASK}: PP to {target}")

    def pcp(self) -> tuple[str, str] | None:
        """(module, routine) of the program pointer, or None."""
        with self.lock:
            if self.pp is None:
                return None
            routine = self.program.interp.find_routine_py(self.pp)
            module = next((m.name for k, m in self.modules.items() if routine and k == routine.module), "")
            return module, self.pp

    def start(self, remote: bool = True) -> None:
        """Start the program where PP stands. ``remote``: over RWS (AUTO only); else the pendant's Start button
        (in a manual mode: with the enabling device held, which turns the motors on)."""
        with self.lock:
            if remote and self.op_mode != "auto":
                raise RWSError(
                    403,
                    f"start: the controller is in {OPMODES[self.op_mode]}; remote start needs AUTO (in the manual "
                    "modes the operator starts the program on the FlexPendant, holding the enabling device)",
                )
            if self.pp is None:
                raise RWSError(400, "start: no program pointer: resetpp or set-pp-routine first")
            enabling = not remote and self.op_mode != "auto"  # the operator holds the enabling device
            if enabling:
                self.motors_on = True
            elif self.ctrl_state != "motoron":
                raise RWSError(409, f"start: the motors are off ({self.ctrl_state}): turn them on first")
            if not self.started:
                self.program.signals["doMotorsOn"] = 1
                self.program_url = self.program.start()
                self.log_event(1, "Program started", f"{TASK} at {self.pp}")
            else:
                if enabling:
                    self.program.enabling_device(True)
                try:
                    self.program.press_start()
                except ControllerStateError as e:
                    raise RWSError(409, f"start: {e}") from None

    def stop(self) -> None:
        with self.lock:
            if self.started:
                self.program.press_stop()

    def set_motors(self, state: str) -> None:
        with self.lock:
            if state == "motoroff":
                self.motors_on = False
                if self.started and self.program.motors_on:
                    self.program.motors_off_fault("motors off over RWS")
            elif state == "motoron":
                if self.op_mode != "auto":
                    raise RWSError(403, "motoron: in the manual modes the motors come on with the enabling device")
                self.motors_on = True
                if self.started:
                    try:
                        self.program.motors_on_button()
                    except ControllerStateError as e:
                        raise RWSError(409, str(e)) from None
            else:
                raise RWSError(400, f"ctrl-state={state!r}: use motoron or motoroff")

    def symbol(self, parts: list[str]) -> tuple[str, str]:
        """(value text, qualified name) of RAPID data ``[T_ROB1, MODULE?, NAME]``."""
        with self.lock:
            if len(parts) not in (2, 3) or parts[0].upper() != TASK:
                raise RWSError(404, f"RAPID/{'/'.join(parts)}: name data as RAPID/{TASK}/[MODULE/]NAME")
            name = ":".join(parts[1:])
            try:
                value = self.program.interp.get(name)
            except Exception as e:  # no such data, or an ambiguous LOCAL name
                raise RWSError(400, f"RAPID/{'/'.join(parts)}: {e}") from None
            _need_value_type(value, parts, "read")
            return format_value(value), name

    def persistents(self) -> list[dict]:
        """The task's PERS data as RWS's symbol search lists them (``symburl``, ``name``, ``dattyp``; verify)."""
        with self.lock:
            interp = self.program.interp
            names = {n.lower(): n for n in interp.module_names}
            found = [(interp._owner.get(k, ""), ref) for k, ref in interp.globals.items()]
            found += [(mod, ref) for mod, table in interp.local_data.items() for ref in table.values()]
            out = []
            for mod, ref in found:
                if ref.cell.kind == "PERS":
                    url = f"RAPID/{TASK}/{names.get(mod, mod)}/{ref.cell.name}"
                    item = {"_type": "rap-symproplist-search", "_title": url, "symburl": url, "name": ref.cell.name}
                    out.append({**item, "symtyp": "per", "dattyp": ref.cell.type or ""})
            return out

    def set_symbol(self, session: str | None, parts: list[str], value: str) -> None:
        with self.lock:
            if self.op_mode != "auto":
                self._need_master(session, "setting RAPID data in a manual mode")
            _, name = self.symbol(parts)
            ref = self.program.interp.ref(name)
            if ref.cell.kind == "CONST":
                raise RWSError(400, f"RAPID/{'/'.join(parts)} is a CONST: it changes only in the module's file")
            current = self.program.interp.get(name)
            _need_value_type(current, parts, "set")
            try:
                self.program.interp.set(name, _parse_value(value, current))
            except Exception as e:
                raise RWSError(400, f"RAPID/{'/'.join(parts)}: value {value!r} refused: {e}") from None

    def close(self) -> None:
        with self.lock:
            if self.program is not None and self.program.thread.is_alive():
                self.program.stop()
            self._tmp.cleanup()


def _need_value_type(value, parts: list[str], what: str) -> None:
    """RAPID's non-value types (``clock``, ``iodev``, ``socketdev``, ``rawbytes``, signals, zones) have no value
    to show or assign (RAPID reference, "Basic characteristics: data types": non-value data types cannot be
    used in value-oriented operations), so RWS neither reads nor writes them here (400, verify the answer)."""
    if isinstance(value, (ClockVar, Opaque, RawBytes)):
        kind = "clock" if isinstance(value, ClockVar) else ("rawbytes" if isinstance(value, RawBytes) else value.type)
        raise RWSError(400, f"RAPID/{'/'.join(parts)} is a {kind}, a non-value data type: it cannot be {what} over RWS")


def _keep_persistents(old: ControllerEmulator | None, new: ControllerEmulator, skip: str) -> None:
    """Every PERS of ``new`` that ``old`` had too, outside module ``skip`` (the one loaded or unloaded), keeps
    its current value: loading a module leaves the other modules' data alone (RAPID reference, "Persistent
    data": a PERS's current value is stored in its module and kept; only the module's own file holds its
    initial value). A module loaded again with replace starts from its file's values, as a fresh module."""
    if old is None:
        return
    targets = {(m, n): r for m, n, r in _persistent_refs(new.interp)}
    for mod, name, ref in _persistent_refs(old.interp):
        target = targets.get((mod, name))
        if mod != skip and target is not None and target.cell.type == ref.cell.type:
            target.cell.value = copy_value(ref.cell.value)


def _persistent_refs(interp) -> list:
    """(module, name, ref) of every PERS in a task, module and name in lower case."""
    found = [(interp._owner.get(k, ""), k, ref) for k, ref in interp.globals.items()]
    found += [(mod, k, ref) for mod, table in interp.local_data.items() for k, ref in table.items()]
    return [(m, n, r) for m, n, r in found if r.cell.kind == "PERS"]


_TOKEN = re.compile(r'\s*(?:(\[)|(\])|(,)|"([^"]*)"|(TRUE|FALSE)\b|([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?))', re.I)


def _parse_value(text: str, like):
    """A value in RAPID's text form (``3``, ``TRUE``, ``"abc"``, ``[1,[2,3],FALSE]``) as the interpreter assigns
    it (aggregates as lists); the interpreter then checks it against the data's type."""
    pos, stack, out = 0, [[]], None
    text = text.strip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise ValueError(f"cannot read {text[pos : pos + 20]!r}")
        pos = m.end()
        if m.group(1):
            stack.append([])
        elif m.group(2):
            if len(stack) < 2:
                raise ValueError("unbalanced ]")
            done = stack.pop()
            stack[-1].append(done)
        elif m.group(3):
            continue
        elif m.group(4) is not None:
            stack[-1].append(m.group(4))
        elif m.group(5):
            stack[-1].append(m.group(5).upper() == "TRUE")
        else:
            stack[-1].append(float(m.group(6)))
    if len(stack) != 1 or len(stack[0]) != 1:
        raise ValueError("one value, with balanced brackets")
    out = stack[0][0]
    if isinstance(like, bool) != isinstance(out, bool) or isinstance(like, str) != isinstance(out, str):
        raise ValueError(f"a {type(like).__name__} value is expected")
    return out


# ====================================================================================================== HTTP
class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"
    timeout = 10  # a silent client's connection is closed after this many seconds

    def log_message(self, format, *args):  # noqa: A002 - the base class's signature
        pass

    def do_GET(self):
        self._serve("GET")

    def do_POST(self):
        self._serve("POST")

    def do_PUT(self):
        self._serve("PUT")

    def do_DELETE(self):
        self._serve("DELETE")

    # ---- plumbing ---------------------------------------------------------------------------------------
    def _serve(self, method: str) -> None:
        """Every request: its body read whole (Content-Length, or chunked), then authenticated, then served.
        Whatever the request, the client gets an answer with RWS's error body (finding 14)."""
        self._cookie = []
        try:
            body = self._read_body()
        except RWSError as e:  # the body's framing is unknown: answer, then close the connection
            self.close_connection = True
            return self._error(e.status, e.msg)
        try:
            session, new_cookie = self.server.authenticate(self, method)
        except RWSError as e:  # 503: no room for another session
            return self._error(e.status, e.msg, e.code)
        if session is None:
            return self._unauthorized()
        self._cookie = new_cookie
        self._session = session
        url = urlsplit(self.path)
        try:
            # strictly UTF-8: %ff and %fe are not both U+FFFD, so two names never land on one file (finding 13)
            path = unquote(url.path, errors="strict").rstrip("/") or "/"
        except UnicodeDecodeError:
            return self._error(400, f"{url.path}: the path's %-escapes are not UTF-8")
        query = {k: v[-1] for k, v in parse_qs(url.query, keep_blank_values=True).items()}
        try:
            if path.startswith("/fileservice"):
                return self._fileservice(method, path[len("/fileservice") :].lstrip("/"), body, query)
            form = {k: v[-1] for k, v in parse_qs(body.decode("utf-8", "replace"), keep_blank_values=True).items()}
            self.server.route(self, method, path, query, form)
        except RWSError as e:
            self._error(e.status, e.msg, e.code)
        except Exception as e:  # a fault of the emulator: answered, and the server serves on
            self._error(500, f"internal error: {type(e).__name__}: {e}")

    def _read_body(self) -> bytes:
        """The request's body (RFC 9112, section 6: chunked, or Content-Length, or none). A length that is not a
        number, or a negative one, is a 400; a body over MAX_BODY a 413."""
        if "chunked" in (self.headers.get("Transfer-Encoding") or "").lower():
            return self._read_chunked()
        text = (self.headers.get("Content-Length") or "0").strip()
        if not text.isdigit():
            raise RWSError(400, f"Content-Length: {text!r} is not a length in bytes")
        length = int(text)
        if length > MAX_BODY:
            raise RWSError(413, f"request body of {length} bytes: at most {MAX_BODY}")
        body = self.rfile.read(length) if length else b""
        if len(body) != length:
            raise RWSError(400, f"the body ended after {len(body)} of {length} bytes")
        return body

    def _read_chunked(self) -> bytes:
        body = bytearray()
        while True:
            line = self.rfile.readline(1024)
            try:
                size = int(line.split(b";")[0].strip(), 16)
            except ValueError:
                raise RWSError(400, f"chunked body: {line[:40]!r} is not a chunk size") from None
            if size < 0 or len(body) + size > MAX_BODY:
                raise RWSError(413 if size > 0 else 400, f"chunked body: at most {MAX_BODY} bytes")
            if size == 0:
                while self.rfile.readline(1024) not in (b"\r\n", b"\n", b""):  # trailer fields, then the end
                    pass
                return bytes(body)
            chunk = self.rfile.read(size)
            if len(chunk) != size or self.rfile.readline(1024) not in (b"\r\n", b"\n"):
                raise RWSError(400, "chunked body: a chunk is cut short")
            body += chunk

    def _send(self, status: int, body: bytes = b"", ctype: str = "application/json") -> None:
        self.send_response(status)
        if body or status != 204:
            self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        if getattr(self, "_cookie", None):
            for c in self._cookie:
                self.send_header("Set-Cookie", c)
        self.end_headers()
        if body:
            self.wfile.write(body)

    def state(self, items: list[dict], status: int = 200) -> None:
        base = f"http://{self.headers.get('Host', '127.0.0.1')}/"
        doc = {"_links": {"base": {"href": base}}, "_embedded": {"_state": items}}
        self._send(status, json.dumps(doc).encode())

    def _error(self, status: int, msg: str, code: int | None = None) -> None:
        code = -status if code is None else code
        doc = {"_links": {}, "_embedded": {"_type": "status", "status": {"code": code, "msg": msg}}}
        self._send(status, json.dumps(doc).encode())

    def _unauthorized(self) -> None:
        nonce = self.server.new_nonce()
        doc = {"_links": {}, "_embedded": {"_type": "status", "status": {"code": -401, "msg": "401 Unauthorized"}}}
        body = json.dumps(doc).encode()
        self.send_response(401)
        self.send_header(
            "WWW-Authenticate",
            f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", opaque="{self.server.opaque}", algorithm=MD5',
        )
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    # ---- the file service --------------------------------------------------------------------------------
    def _fileservice(self, method: str, rel: str, body: bytes, query: dict) -> None:
        vc = self.server.controller
        with vc.lock:
            target = vc.file_path(rel)
            if method == "GET":
                if target.is_dir():
                    items = [
                        {
                            "_type": "fs-dir" if p.is_dir() else "fs-file",
                            "_title": p.name,
                            "fs-size": str(p.stat().st_size),
                        }
                        for p in sorted(target.iterdir())
                    ]
                    return self.state(items)
                if target.is_file():
                    return self._send(200, target.read_bytes(), "application/octet-stream")
                raise RWSError(404, f"{rel}: no such file or folder")
            if method == "PUT":
                if not target.parent.is_dir():
                    raise RWSError(404, f"{rel}: folder {target.parent.name} does not exist (create it first)")
                if target.is_dir():
                    raise RWSError(409, f"{rel} is a folder")
                existed = target.exists()
                target.write_bytes(body)
                return self._send(200 if existed else 201)
            if method == "DELETE":
                if target == vc.home:  # $HOME itself: every later upload would fail (finding 13; verify the answer)
                    raise RWSError(403, f"{rel}: the home folder cannot be removed")
                if target.is_dir():
                    if any(target.iterdir()):
                        raise RWSError(409, f"{rel}: the folder is not empty")
                    target.rmdir()
                elif target.is_file():
                    target.unlink()
                else:
                    raise RWSError(404, f"{rel}: no such file or folder")
                return self._send(204)
            if method == "POST":
                form = {k: v[-1] for k, v in parse_qs(body.decode("utf-8", "replace")).items()}
                if form.get("fs-action") != "create" or not form.get("fs-newname"):
                    raise RWSError(400, "POST on the file service: fs-action=create with fs-newname=FOLDER")
                if not target.is_dir():
                    raise RWSError(404, f"{rel}: no such folder")
                name = form["fs-newname"]
                parts = name.strip("/").split("/")
                if any(part in ("", "..", ".") for part in parts):
                    raise RWSError(400, f"fs-newname={name!r}: folder names, '/' between them, no '..' or '.'")
                new = target.joinpath(*parts)  # a/b: the folders on the way are created too (verify)
                if new.exists():
                    raise RWSError(409, f"{rel}/{name} exists")
                new.mkdir(parents=True)
                return self._send(201)
        raise RWSError(405, f"{method} is not served on the file service")


_SYMBOL = re.compile(r"/rw/rapid/symbol/data/RAPID/(.+)")


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(
        self,
        port: int,
        controller: VirtualController,
        user: str,
        password: str,
        max_sessions: int = MAX_SESSIONS,
        session_idle_s: float = SESSION_IDLE_S,
    ):
        super().__init__(("127.0.0.1", port), _Handler)
        self.controller = controller
        self.user, self.password = user, password
        self.max_sessions, self.session_idle_s = max_sessions, session_idle_s
        self.opaque = secrets.token_hex(8)
        self._nonces: dict[str, int] = {}  # nonce -> the last nc seen
        self._sessions: dict[str, float] = {}  # session -> when it was last used (time.monotonic())
        self._lock = threading.Lock()

    def new_nonce(self) -> str:
        with self._lock:
            nonce = secrets.token_hex(16)
            self._nonces[nonce] = 0
            while len(self._nonces) > MAX_NONCES:
                self._nonces.pop(next(iter(self._nonces)))
            return nonce

    def authenticate(self, h: _Handler, method: str) -> tuple[str | None, list[str]]:
        """(session, cookies to set): a valid digest answer (RFC 7616, MD5, qop=auth) or a known session
        cookie; (None, []) otherwise. A wrong Authorization fails even with a session cookie. A session unused
        for ``session_idle_s`` has ended (its mastership and RMMP with it, finding 8); a new one beyond
        ``max_sessions`` is refused with 503 (finding 11; abb-robot-client reads 503 as "too many active
        connections")."""
        cookies = dict(c.strip().split("=", 1) for c in (h.headers.get("Cookie") or "").split(";") if "=" in c.strip())
        session = cookies.get("ABBCX")
        self.expire_sessions()
        auth = h.headers.get("Authorization")
        if auth is None:
            return (self._touch(session), []) if session in self._sessions else (None, [])
        if not self._digest_ok(auth, method, h.path):
            return None, []
        if session in self._sessions:
            return self._touch(session), []
        with self._lock:
            if len(self._sessions) >= self.max_sessions:
                raise RWSError(
                    503,
                    f"too many sessions: {self.max_sessions} are open; log out of one (GET /logout) or wait until "
                    f"one has been idle for {self.session_idle_s:g} s",
                )
            session = secrets.token_hex(12)
            self._sessions[session] = time.monotonic()
        return session, [f"-http-session-={session}::http-session::; path=/", f"ABBCX={session}; path=/"]

    def _touch(self, session: str) -> str:
        with self._lock:
            self._sessions[session] = time.monotonic()
        return session

    def expire_sessions(self) -> None:
        """End every session unused for ``session_idle_s``."""
        now = time.monotonic()
        with self._lock:
            idle = [s for s, used in self._sessions.items() if now - used > self.session_idle_s]
        for s in idle:
            self.logout(s)

    def _digest_ok(self, header: str, method: str, path: str) -> bool:
        if not header.startswith("Digest "):
            return False
        f = {k: a or b for k, a, b in re.findall(r'(\w+)=(?:"([^"]*)"|([^\s,]+))', header[7:])}
        need = ("username", "realm", "nonce", "uri", "response", "qop", "nc", "cnonce")
        if any(k not in f for k in need) or f["qop"] != "auth" or f.get("algorithm", "MD5").upper() != "MD5":
            return False
        if f["username"] != self.user or f["realm"] != REALM or f["uri"] != path:
            return False
        try:
            nc = int(f["nc"], 16)
        except ValueError:
            return False
        with self._lock:
            last = self._nonces.get(f["nonce"])
            if last is None or nc <= last:  # an unknown nonce or a replayed count
                return False
            md5 = lambda s: hashlib.md5(s.encode()).hexdigest()  # noqa: S324 - RFC 7616's MD5 digest
            ha1 = md5(f"{self.user}:{REALM}:{self.password}")
            ha2 = md5(f"{method}:{f['uri']}")
            expected = md5(f"{ha1}:{f['nonce']}:{f['nc']}:{f['cnonce']}:auth:{ha2}")
            if not secrets.compare_digest(expected, f["response"]):
                return False
            self._nonces[f["nonce"]] = nc
            return True

    def logout(self, session: str) -> None:
        with self._lock:
            self._sessions.pop(session, None)
        self.controller.end_session(session)

    # ---- /rw, /users, /logout: the route table ----------------------------------------------------------
    def route(self, h: _Handler, method: str, path: str, query: dict, form: dict) -> None:
        """Serve ``method path`` from :data:`ROUTES` (a pattern matched whole against the path; its groups go to
        the handler). An action the resource does not take, or a resource not in the table: 404."""
        action = query.get("action")
        for (m, pattern), handler in ROUTES.items():
            match = pattern.fullmatch(path) if m == method else None
            if match is not None and handler(self, h, query, form, *match.groups()) is not _NO_SUCH_ACTION:
                return
        raise RWSError(404, f"{method} {path}{'?action=' + action if action else ''}: no such resource")

    def _logout(self, h: _Handler, query: dict, form: dict) -> None:
        self.logout(h._session)
        h._send(204)

    def _get_system(self, h: _Handler, query: dict, form: dict) -> None:
        h.state(self._system() + self._options())

    def _get_options(self, h: _Handler, query: dict, form: dict) -> None:
        h.state(self._options())

    def _get_ctrlstate(self, h: _Handler, query: dict, form: dict) -> None:
        h.state([{"_type": "pnl-ctrlstate", "_title": "ctrlstate", "ctrlstate": self.controller.ctrl_state}])

    def _set_ctrlstate(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.set_motors(form.get("ctrl-state", ""))
        h._send(204)

    def _get_opmode(self, h: _Handler, query: dict, form: dict) -> None:
        h.state([{"_type": "pnl-opmode", "_title": "opmode", "opmode": OPMODES[self.controller.op_mode]}])

    def _get_speedratio(self, h: _Handler, query: dict, form: dict) -> None:
        ratio = str(self.controller.speed_ratio)
        h.state([{"_type": "pnl-speedratio", "_title": "speedratio", "speedratio": ratio}])

    def _set_speedratio(self, h: _Handler, query: dict, form: dict) -> None:
        try:
            ratio = int(float(form.get("speed-ratio", "")))
        except ValueError:
            raise RWSError(400, "speed-ratio: a whole percentage 0..100") from None
        if not 0 <= ratio <= 100:
            raise RWSError(400, f"speed-ratio={ratio}: 0..100")
        self.controller.speed_ratio = ratio
        h._send(204)

    def _request_mastership(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.request_mastership(h._session)
        h._send(204)

    def _release_mastership(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.release_mastership(h._session)
        h._send(204)

    def _get_rmmp(self, h: _Handler, query: dict, form: dict) -> None:
        h.state([{"_type": "user-rmmp", "_title": "state", **self.controller.rmmp_state(h._session)}])

    def _request_rmmp(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.request_rmmp(h._session, form.get("privilege", ""))
        h._send(202)

    def _cancel_rmmp(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.cancel_rmmp(h._session)
        h._send(204)

    def _answer_rmmp(self, h: _Handler, query: dict, form: dict) -> None:
        raise RWSError(
            403,
            "action=set answers an RMMP request: a local client's (the FlexPendant's) call; a remote client cannot "
            "grant or deny one, not even its own (verify)",
        )

    def _poll_rmmp(self, h: _Handler, query: dict, form: dict) -> None:
        status = self.controller.poll_rmmp(h._session)
        item = {"_type": "user-rmmp-poll", "_title": "state", "status": status}
        if status == "NO SUCH REQUEST":
            item["code"] = str(CODE_NO_RMMP_REQUEST)
        h.state([item])

    def _get_execution(self, h: _Handler, query: dict, form: dict) -> None:
        state = self.controller.exec_state
        h.state([{"_type": "rap-execution", "_title": "execution", "ctrlexecstate": state, "cycle": "forever"}])

    def _start(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.start(remote=True)
        h._send(204)

    def _stop(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.stop()
        h._send(204)

    def _resetpp(self, h: _Handler, query: dict, form: dict) -> None:
        self.controller.set_pp(h._session, None)
        h._send(204)

    def _get_task(self, h: _Handler, query: dict, form: dict) -> None:
        h.state([self._task()])

    def _loadmod(self, h: _Handler, query: dict, form: dict) -> None:
        if "modulepath" not in form:
            raise RWSError(400, "loadmod: modulepath=$HOME/FILE")
        replace = form.get("replace", "false").lower() == "true"
        self.controller.load_module(h._session, form["modulepath"], replace)
        h._send(204)

    def _unloadmod(self, h: _Handler, query: dict, form: dict) -> None:
        if "module" not in form:
            raise RWSError(400, "unloadmod: module=NAME")
        self.controller.unload_module(h._session, form["module"])
        h._send(204)

    def _activate(self, h: _Handler, query: dict, form: dict) -> None:
        h._send(204)

    def _deactivate(self, h: _Handler, query: dict, form: dict) -> None:
        raise RWSError(400, f"{TASK} is the motion task: it stays active")

    def _get_modules(self, h: _Handler, query: dict, form: dict) -> None:
        vc = self.controller
        with vc.lock:
            items = [
                {
                    "_type": "rap-module-info-li",
                    "_title": m.name,
                    "name": m.name,
                    "type": "SysMod" if m.sysmod else "ProgMod",
                }
                for m in vc.modules.values()
            ]
        h.state(items)

    def _get_modules_of_task(self, h: _Handler, query: dict, form: dict):
        """``/rw/rapid/modules?task=T_ROB1`` (abb_librws's form): the modules of the one task there is."""
        if query.get("task") != TASK:
            return _NO_SUCH_ACTION
        return self._get_modules(h, query, form)

    def _get_pcp(self, h: _Handler, query: dict, form: dict) -> None:
        where = self.controller.pcp()
        item = {"_type": "pcp-info", "_title": "progpointer", "modulename": "", "routinename": ""}
        if where is not None:
            item.update(modulename=where[0], routinename=where[1])
        h.state([item])

    def _set_pp_routine(self, h: _Handler, query: dict, form: dict) -> None:
        if not form.get("routine"):
            raise RWSError(400, "set-pp-routine: routine=NAME")
        self.controller.set_pp(h._session, form["routine"])
        h._send(204)

    def _get_elog(self, h: _Handler, query: dict, form: dict) -> None:
        h.state(self._elog())

    def _search_symbols(self, h: _Handler, query: dict, form: dict) -> None:
        if form.get("symtyp", "per") != "per":
            raise RWSError(400, "search-symbols: the emulator lists persistents only (symtyp=per)")
        h.state(self.controller.persistents())

    def _get_symbol(self, h: _Handler, query: dict, form: dict, name: str) -> None:
        parts = name.split("/")
        value, _ = self.controller.symbol(parts)
        h.state([{"_type": "rap-data", "_title": f"RAPID/{'/'.join(parts)}", "value": value}])

    def _set_symbol(self, h: _Handler, query: dict, form: dict, name: str) -> None:
        if "value" not in form:
            raise RWSError(400, "action=set: value=TEXT")
        self.controller.set_symbol(h._session, name.split("/"), form["value"])
        h._send(204)

    def _system(self) -> list[dict]:
        vc = self.controller
        return [
            {
                "_type": "sys-system-li",
                "_title": "system",
                "name": vc.system_name,
                "rwversion": ROBOTWARE_VERSION,
                "rwversionname": ROBOTWARE_VERSION,
                "sysid": "{emulator}",
            }
        ]

    def _options(self) -> list[dict]:
        return [{"_type": "sys-option-li", "_title": o, "option": str(OPTIONS[o])} for o in self.controller.options]

    def _task(self) -> dict:
        vc = self.controller
        running = vc.exec_state == "running"
        return {
            "_type": "rap-task-li",
            "_title": TASK,
            "name": TASK,
            "type": "norm",
            "taskstate": "started" if running else "linked",
            "excstate": "started" if running else ("ready" if vc.pp else "uninitialized"),
            "active": "On",
            "motiontask": "TRUE",
        }

    def _elog(self) -> list[dict]:
        now_wall, now_mono = time.time(), time.monotonic()
        out = []
        for seq, e in enumerate(self.controller.events(), start=1):
            stamp = time.strftime("%Y-%m-%d T  %H:%M:%S", time.localtime(now_wall - (now_mono - e.time)))
            out.append(
                {
                    "_type": "elog-message-li",
                    "_title": f"/rw/elog/0/{seq}",
                    "msgtype": str(e.msgtype),
                    "code": str(e.code),
                    "tstamp": stamp,
                    "title": e.title,
                    "desc": e.desc,
                    "conseqs": "",
                    "causes": "",
                    "actions": "",
                    "argc": "0",
                }
            )
        return out[::-1]  # newest first, as the pendant lists them (verify)


_NO_SUCH_ACTION = object()  # a handler's answer: this resource does not take the request's action


def _actions(**by_action):
    """One handler for a resource that takes ``?action=``: the action's handler, or none (404)."""

    def handler(server: _Server, h: _Handler, query: dict, form: dict, *groups):
        chosen = by_action.get(query.get("action") or "")
        return _NO_SUCH_ACTION if chosen is None else chosen(server, h, query, form, *groups)

    return handler


def _path(pattern: str) -> re.Pattern:
    return re.compile(re.escape(pattern).replace(re.escape("{TASK}"), TASK))


# (method, path pattern) -> handler: every resource the emulator serves besides the file service. A resource that
# takes actions maps them by name (no action: the "" entry).
ROUTES = {
    ("GET", _path("/logout")): _Server._logout,
    ("GET", _path("/rw/system")): _Server._get_system,
    ("GET", _path("/rw/system/options")): _Server._get_options,
    ("GET", _path("/rw/panel/ctrlstate")): _Server._get_ctrlstate,
    ("POST", _path("/rw/panel/ctrlstate")): _actions(setctrlstate=_Server._set_ctrlstate),
    ("GET", _path("/rw/panel/opmode")): _Server._get_opmode,
    ("GET", _path("/rw/panel/speedratio")): _Server._get_speedratio,
    ("POST", _path("/rw/panel/speedratio")): _actions(setspeedratio=_Server._set_speedratio),
    ("POST", _path("/rw/mastership")): _actions(
        request=_Server._request_mastership, release=_Server._release_mastership
    ),
    ("GET", _path("/users/rmmp")): _Server._get_rmmp,
    ("POST", _path("/users/rmmp")): _actions(
        **{"": _Server._request_rmmp, "cancel": _Server._cancel_rmmp, "set": _Server._answer_rmmp}
    ),
    ("GET", _path("/users/rmmp/poll")): _Server._poll_rmmp,
    ("GET", _path("/rw/rapid/execution")): _Server._get_execution,
    ("POST", _path("/rw/rapid/execution")): _actions(
        start=_Server._start, stop=_Server._stop, resetpp=_Server._resetpp
    ),
    ("GET", _path("/rw/rapid/tasks")): _Server._get_task,
    ("GET", _path("/rw/rapid/tasks/{TASK}")): _Server._get_task,
    ("POST", _path("/rw/rapid/tasks/{TASK}")): _actions(
        loadmod=_Server._loadmod,
        unloadmod=_Server._unloadmod,
        activate=_Server._activate,
        deactivate=_Server._deactivate,
    ),
    ("GET", _path("/rw/rapid/tasks/{TASK}/modules")): _Server._get_modules,
    ("GET", _path("/rw/rapid/modules")): _Server._get_modules_of_task,
    ("GET", _path("/rw/rapid/tasks/{TASK}/pcp")): _Server._get_pcp,
    ("POST", _path("/rw/rapid/tasks/{TASK}/pcp")): _actions(**{"set-pp-routine": _Server._set_pp_routine}),
    ("GET", _path("/rw/elog/0")): _Server._get_elog,
    ("GET", _path("/rw/elog")): _Server._get_elog,
    ("POST", _path("/rw/rapid/symbols")): _actions(**{"search-symbols": _Server._search_symbols}),
    ("GET", _SYMBOL): _Server._get_symbol,
    ("POST", _SYMBOL): _actions(set=_Server._set_symbol),
}


class RWSEmulator:
    """The web services of a :class:`VirtualController` on ``http://127.0.0.1:PORT`` (0: a free port); a context
    manager. ``max_sessions`` and ``session_idle_s``: how many sessions the server keeps and how long an unused one
    lasts (:data:`MAX_SESSIONS`, :data:`SESSION_IDLE_S`). Extra keyword arguments go to the controller (e.g.
    ``operator``, ``op_mode``, ``options``)."""

    def __init__(
        self,
        port: int = 0,
        user: str = DEFAULT_USER,
        password: str = DEFAULT_PASSWORD,
        max_sessions: int = MAX_SESSIONS,
        session_idle_s: float = SESSION_IDLE_S,
        **controller,
    ):
        if not 0 <= port <= 65535:
            raise ValueError(f"port {port}: 0..65535 (0: a free port)")
        self.controller = VirtualController(**controller)
        try:
            self._server = _Server(port, self.controller, user, password, max_sessions, session_idle_s)
        except BaseException:
            self.controller.close()  # its temporary $HOME goes too
            raise
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)

    def start(self) -> str:
        self._thread.start()
        return self.url

    def stop(self) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
            self._thread.join(5)
        self._server.server_close()
        self.controller.close()

    def __enter__(self) -> RWSEmulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def main(
    rws: str,
    options: str | None = None,
    op_mode: str = "manual_reduced",
    statement_cost_us: float = STATEMENT_COST_US,
    main_entry: str = "main",
    serve_s: float | None = None,
    operator: str = "grant",
    max_sessions: int = MAX_SESSIONS,
    session_idle_s: float = SESSION_IDLE_S,
) -> int:
    """Serve RWS on ``rws`` (``127.0.0.1:PORT``; 0: a free port) until interrupted, terminated (SIGTERM) or
    ``serve_s`` seconds have passed; prints the URL as its first line, then each program URL as the program
    starts. Either way the temporary $HOME is removed. A bad argument raises ValueError (the CLI prints its one
    line and exits 2); a port it cannot bind is one line on stderr and exit status 1."""
    host, _, port = rws.rpartition(":")
    if host not in ("127.0.0.1", "localhost") or not port.isdigit():
        raise ValueError(f"--rws {rws!r}: the emulator serves 127.0.0.1:PORT only (0: a free port)")
    if int(port) > 65535:
        raise ValueError(f"--rws {rws!r}: a port is 0..65535 (0: a free port)")
    if max_sessions < 1 or not session_idle_s > 0:
        raise ValueError(f"max_sessions={max_sessions}, session_idle_s={session_idle_s}: both must be positive")
    try:
        emu = RWSEmulator(
            int(port),
            max_sessions=max_sessions,
            session_idle_s=session_idle_s,
            options=options or (),
            op_mode=op_mode,
            statement_cost_us=statement_cost_us,
            main_entry=main_entry,
            operator=operator,
        )
    except OSError as e:
        print(f"--rws {rws}: cannot serve there: {e.strerror or e}", file=sys.stderr)
        return 1
    previous = None
    if threading.current_thread() is threading.main_thread():  # SIGTERM ends it as Ctrl-C does: cleaned up
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        print(emu.start(), flush=True)
        deadline = None if serve_s is None else time.monotonic() + serve_s
        shown = None
        while deadline is None or time.monotonic() < deadline:
            url = emu.controller.program_url
            if url and url != shown:
                print(f"program started: the PC connects to {url}", flush=True)
                shown = url
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


__all__ = ["RWSEmulator", "RWSError", "VirtualController", "main"]
