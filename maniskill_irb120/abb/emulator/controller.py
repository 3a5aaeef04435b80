"""The emulated IRC5 (:class:`ControllerEmulator`): one task built from the shipped modules as an integrator loads
them (the core ``IRB120Server.mod``, the channel module, ``IRB120Zone.sys`` with 608-1), run with the routines of
``builtins.py`` on ``robot.py``'s IRB 120, serving a pty (serial) or a loopback TCP socket; and the pendant's
commands out of process (:data:`PENDANT`). See docs/emulator.md.

    maniskill-irb120 emulator --listen tcp://127.0.0.1:0      # first line printed: the URL to connect to
    maniskill-irb120 emulator --pendant -                     # and the pendant's buttons from stdin (see PENDANT)
"""

from __future__ import annotations

import math
import os
import re
import socket
import sys
import threading
import time
from collections.abc import Iterable
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from maniskill_irb120.abb.emulator.builtins import CONTROLLER, OP_MODE_NAMES
from maniskill_irb120.abb.emulator.channel import Channel, parse_faults
from maniskill_irb120.abb.emulator.motion import MANUAL_REDUCED_TCP_MM_S
from maniskill_irb120.abb.emulator.pendant import ControllerStateError, Pendant
from maniskill_irb120.abb.emulator.rapid import Interpreter, RapidStopped, RapidSyntaxError, parse_options
from maniskill_irb120.abb.emulator.rapid.execution import PPToMain
from maniskill_irb120.abb.emulator.robot import EmulatedIRB120
from maniskill_irb120.robot.irb120 import IRB120Metalwork

REST_DEG = tuple(np.degrees(IRB120Metalwork.keyframes["rest"].qpos[:6]))  # where the sim's episodes start


ENTRY = "IRB120Server"  # the core module's entry routine (the task's main entry on a controller)
ZONE_POWER_ON = "IRB120ZonePowerOn"  # IRB120Zone.sys's POWER ON event routine
CHANNEL_MODULES = {"serial": "IRB120Serial.mod", "tcp": "IRB120Socket.mod"}


def rapid_file(name: str) -> Path:
    """A shipped RAPID file (assets/rapid/NAME)."""
    return Path(str(resources.files("maniskill_irb120.assets").joinpath("rapid", name)))


def shipped_module() -> Path:
    """The shipped core server module (protocol, checks, motion, replies)."""
    return rapid_file("IRB120Server.mod")


def server_source(
    channel: str, rapid: str | Path | None = None, zone: bool = True, pc_address: str | None = None
) -> str:
    """The modules a controller running the server on ``channel`` has loaded, as one source: the core (``rapid``
    instead of the shipped one if given), the channel module and, with ``zone``, the world-zone system module.
    ``pc_address``: the TCP build's PC_ADDRESS set to it, as the integrator edits it before loading."""
    files = [Path(rapid) if rapid else shipped_module(), rapid_file(CHANNEL_MODULES[channel])]
    if zone:
        files.append(rapid_file("IRB120Zone.sys"))
    text = "\n".join(f.read_text() for f in files)
    if pc_address is not None and channel == "tcp":
        text, n = re.subn(r'(CONST string PC_ADDRESS := )"[^"]*"', rf'\g<1>"{pc_address}"', text)
        if n != 1:
            raise ValueError("the socket module has no single PC_ADDRESS constant to set")
    return text


# The default module of a new IRC5 task (what a fresh controller holds before anything is loaded): a second global
# PROC main beside it is an ambiguous name, so a server loaded next to it declares its main LOCAL.
STOCK_MAIN_MODULE = """MODULE MainModule
    PROC main()
        !Add your code here
    ENDPROC
ENDMODULE
"""

# What each channel's build needs at the least (docs/real_robot.md): serial, nothing (a licence-free controller);
# tcp, the socket API of 616-1 PC Interface (or 672-1 Socket Messaging).
CHANNEL_OPTIONS: dict[str, tuple[str, ...]] = {"serial": (), "tcp": ("616-1",)}


# The controller time one executed RAPID statement costs: an estimate (no IRC5 was measured for this project;
# measure yours with ClkRead\\HighRes around a loop, docs/real_robot.md). 0 turns the pacing off.
STATEMENT_COST_US = 10.0

RESTART_ROUTINE = "IRB120ServerRestart"  # the core module's RESTART event routine


class MotionSupervisionError(RuntimeError):
    """The robot met an error while moving: the controller stops the program (fatal, no ERROR handler)."""


class ControllerEmulator(Pendant):
    """Runs the server on channel ``serial`` (a pty) or ``tcp`` (127.0.0.1): the core module ``rapid`` (default: the
    shipped one), the shipped channel module for the channel and, with ``zone``, the world-zone system module.

    ``options``: the RobotWare option ids the controller has; None: the least the build needs (serial: none, a
    licence-free controller; tcp: 616-1 PC Interface). The task is refused at load time (:class:`RapidLoadError`)
    if a module names anything of a missing option. ``zone``: load the world-zone system module (None: when
    608-1 World Zones is installed). ``extra_modules``: RAPID texts loaded into the same task (e.g.
    :data:`STOCK_MAIN_MODULE`); ``entry``: the PROC the program starts at (the task's main entry). ``op_mode``:
    the key switch (:data:`OP_MODE_NAMES`), what ``OpMode()`` returns; set :attr:`op_mode` to turn it while the
    program runs. ``statement_cost_us``: the controller time of one RAPID statement (:data:`STATEMENT_COST_US`).
    ``pc_address``: the PC's address the TCP build serves (its PC_ADDRESS constant, as an integrator sets it).
    ``modules``: the task's module texts as the controller holds them (loaded over Robot Web Services,
    ``rws.py``), instead of the shipped files: what was loaded is what runs.

    The operator's controls (Stop, Start, PP to main, emergency stop, the enabling device) and the event log are
    in :class:`~.pendant.Pendant`."""

    def __init__(
        self,
        channel: str = "serial",
        rapid: str | Path | None = None,
        port: int = 0,
        q0_deg=REST_DEG,
        faults: str | None = None,
        baud: int | None = None,
        latency_ms: float = 0.0,
        speed_scale: float = 1.0,
        options: tuple[str, ...] | None = None,
        zone: bool | None = None,
        extra_modules: tuple[str, ...] | list[str] = (),
        entry: str = ENTRY,
        op_mode: str = "manual_reduced",
        statement_cost_us: float = STATEMENT_COST_US,
        pc_address: str = "127.0.0.1",
        modules: tuple[str, ...] | list[str] | None = None,
    ):
        if channel not in CHANNEL_MODULES:
            raise ValueError(f"channel={channel!r}: use 'serial' or 'tcp'")
        self.options = parse_options(CHANNEL_OPTIONS[channel] if options is None else options)
        zone = "608-1" in self.options if zone is None else zone
        self.entry = entry
        if baud is not None and (channel != "serial" or baud <= 0):
            raise ValueError(f"baud={baud!r}: a positive line speed, for the serial channel only")
        if not (math.isfinite(latency_ms) and latency_ms >= 0):
            raise ValueError(f"latency_ms={latency_ms!r}: a finite delay >= 0 ms")
        if not (math.isfinite(speed_scale) and speed_scale > 0):
            raise ValueError(f"speed_scale={speed_scale!r}: a positive factor on the robot's speed")
        self.baud = baud
        self.op_mode = op_mode
        self.channel_kind, self.port = channel, port
        self.zone = zone
        sources = [server_source(channel, rapid, zone, pc_address)] if modules is None else list(modules)
        self.robot = EmulatedIRB120(q0_deg)
        self.robot.speed_scale = speed_scale
        self.op_mode = op_mode  # again, now that the robot exists: its TCP speed cap follows the key switch
        self.signals = {"doGripperOpen": 1, "doMotorsOn": 1, "doEmergencyStop": 0}
        self._init_pendant()
        self.link = Channel(parse_faults(faults), self._injected_fault, baud, latency_ms / 1000)
        self.moves = 0  # motion instructions executed (MoveL, MoveAbsJ): "nothing runs twice" is counted here
        # syntax and load errors (missing options, ambiguous names) surface here, with their module and line
        self.interp = Interpreter(
            [*sources, *extra_modules],
            CONTROLLER,
            options=self.options,
            statement_cost_s=statement_cost_us / 1e6,
            host=self,
        )
        self.interp.supervision = self._motion_supervision
        self.start_routines: list[str] = []  # START event routines: run when the program starts from main
        if self.interp.find_routine_py(RESTART_ROUTINE) is not None:
            self.interp.restart_routines.append(RESTART_ROUTINE)
        self.error: BaseException | None = None
        self.ended = False  # the program returned or stopped with an error (PP to main, then Start)
        self._start_from_main = threading.Event()
        self._shutdown = False
        self._server: socket.socket | None = None
        self._conns: list[socket.socket] = []  # every client connection accepted (closed by stop())
        self._slave: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    @property
    def op_mode(self) -> str:
        """The key switch: ``manual_reduced``, ``auto`` or ``manual_full``; settable while the program runs."""
        return self._op_mode

    @op_mode.setter
    def op_mode(self, mode: str) -> None:
        if mode not in OP_MODE_NAMES:
            raise ValueError(f"op_mode={mode!r}: use one of {sorted(OP_MODE_NAMES)}")
        self._op_mode = mode
        if hasattr(self, "robot"):  # manual reduced speed: the controller caps the TCP at 250 mm/s
            self.robot.max_tcp_speed_mm_s = MANUAL_REDUCED_TCP_MM_S if mode == "manual_reduced" else None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> str:
        """Start the RAPID program; returns the URL a client connects to."""
        if self.channel_kind == "serial":
            self.link.fd, self._slave = os.openpty()
            url = f"serial://{os.ttyname(self._slave)}?baudrate={self.baud or 115200}"
        else:
            self._server = socket.create_server(("127.0.0.1", self.port))
            url = f"tcp://127.0.0.1:{self._server.getsockname()[1]}"
        self.thread.start()
        return url

    def _run(self) -> None:
        try:
            if self.zone:  # the controller ran the system module's POWER ON event routine long before
                self.interp.call(ZONE_POWER_ON)
        except BaseException as e:
            self.error = e
            return
        while not self._shutdown:
            try:
                for name in self.start_routines:
                    self.interp.call(name)
                self.interp.run(self.entry)
                self.ended = True  # the entry routine returned: the program has ended
            except PPToMain:
                self.robot.clear_path()
                self.robot.motion_error = None
            except RapidStopped:
                return
            except BaseException as e:  # a fatal program error: the robot stops, as the IRC5 stops the program
                self.robot.stop(quick=True)
                self.error, self.ended = e, True
                self.log_event(None, "Program stopped by an error", str(e))
            # the program pointer stands at main (or the program has ended): the next Start runs it from the top
            self._start_from_main.wait()
            self._start_from_main.clear()

    def _start_program(self) -> None:
        if self.at_main:
            self.at_main, self.error, self.ended = False, None, False
            self._start_from_main.set()
        else:
            if not self._path_was_stopped:
                self.robot.start()  # the planner goes on with the path it had queued, as an IRC5 does
            self.interp.resume()

    def _motion_supervision(self) -> None:
        """An error the robot met while moving (outside reach, a world zone) stops the program wherever it is:
        it never reaches a RAPID ERROR handler (docs/reference.md, "path errors during execution")."""
        err = self.robot.motion_error
        if err is not None:
            self.robot.motion_error = None
            self.log_event(getattr(err, "code", None), "Motion error", str(err))
            raise MotionSupervisionError(f"motion stopped: {err}")

    def _injected_fault(self, kind: str) -> None:
        if kind == "estop":
            self.emergency_stop()
        else:
            self.motors_off_fault("fault injection")

    def stop(self) -> None:
        self._shutdown = True
        self._start_from_main.set()
        self.interp.request_stop()
        self.thread.join(2)
        self.robot.stop()
        for closer in (
            lambda: self._server and self._server.close(),
            *(conn.close for conn in self._conns),
        ):
            closer()
        for fd in (self.link.fd, self._slave):
            if fd is not None:
                os.close(fd)
        self.link.fd = self._slave = None

    def __enter__(self) -> ControllerEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def accept_client(self, timeout: float) -> tuple[socket.socket, tuple]:
        """A client of the listening socket within ``timeout`` s (TimeoutError if none); :meth:`stop` closes it."""
        self._server.settimeout(timeout)
        conn, peer = self._server.accept()
        self._conns.append(conn)
        return conn, peer


# The pendant's controls as commands (``--pendant``: one or more a line, separated by ``;``), so that a fault and
# the operator's restart can be scripted out of process, as an integrator's test harness drives a cell.
PENDANT = {
    "stop": "the Stop button: the program halts, the robot stops on its path",
    "start": "the Start button: the program goes on where it stood, or from the top after pp-to-main",
    "pp-to-main": "PP to main (the program stopped): UNDO handlers run, the path is cleared",
    "estop": "an emergency stop: motors off, the program halts",
    "reset-estop": "the emergency stop released and reset (the motors stay off)",
    "motors-off": "motors off while the program runs (a guard stop; in manual mode the enabling device let go)",
    "motors-on": "motors on: the enabling device held (manual modes), the Motors On button (auto)",
    "wait": "wait SECONDS before the next command",
    "state": "print the program state, the motors, the emergency stop and the key switch",
    "quit": "stop the emulator",
}


def pendant_command(emu: ControllerEmulator, command: str) -> str:
    """Does one pendant command (:data:`PENDANT`) on ``emu``; returns the line to print: ``pendant: COMMAND: ...``
    with the controller's state after it, or why the controller refused it. A command that is not one of them
    raises ValueError naming it; ``quit`` returns ``pendant: quit``."""
    name, *args = command.split()
    if name not in PENDANT or len(args) != (name == "wait"):
        usage = ", ".join(f"{k} SECONDS" if k == "wait" else k for k in PENDANT)
        raise ValueError(f"pendant command {command!r}: use one of {usage}")
    if name == "wait":
        try:
            seconds = float(args[0])
        except ValueError:
            seconds = math.nan
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"pendant command {command!r}: wait takes a time in seconds >= 0")
        time.sleep(seconds)
    elif name != "state" and name != "quit":
        action = {
            "stop": emu.press_stop,
            "start": emu.press_start,
            "pp-to-main": emu.pp_to_main,
            "estop": emu.emergency_stop,
            "reset-estop": emu.reset_emergency_stop,
            "motors-off": lambda: emu.motors_off_fault("pendant command"),
            "motors-on": lambda: emu.enabling_device(True) if emu.op_mode != "auto" else emu.motors_on_button(),
        }[name]
        try:
            action()
        except ControllerStateError as e:
            return f"pendant: {command}: refused: {e}"
        if emu.interp.is_halted:  # the program stands still when the line is printed
            emu.interp.halted.wait(1.0)
    if name == "quit":
        return "pendant: quit"
    estop = "active" if emu.emergency_stop_active else "off"
    return (
        f"pendant: {command}: program {emu.program_state}, motors {'on' if emu.motors_on else 'off'}, "
        f"emergency stop {estop}, key {emu.op_mode}"
    )


def run_pendant(emu: ControllerEmulator, lines: Iterable[str], out=None, done: threading.Event | None = None) -> None:
    """Runs the pendant commands in ``lines`` (``;`` separates commands on a line, ``#`` starts a comment), printing
    each one's line to ``out`` (stdout); a bad command prints its error and the next goes on. ``quit`` sets
    ``done`` and ends the script."""
    out = out or sys.stdout
    for line in lines:
        for command in line.split("#", 1)[0].split(";"):
            if not command.strip():
                continue
            try:
                print(pendant_command(emu, command.strip()), file=out, flush=True)
            except ValueError as e:
                print(f"pendant: error: {e}", file=out, flush=True)
                continue
            if command.split()[0] == "quit":
                if done is not None:
                    done.set()
                return


def main(
    listen: str = "tcp://127.0.0.1:0",
    rapid: str | None = None,
    fault: str | None = None,
    latency_ms: float = 0.0,
    speed_scale: float = 1.0,
    options: str | None = None,
    op_mode: str = "manual_reduced",
    statement_cost_us: float = STATEMENT_COST_US,
    pc_address: str | None = None,
    pendant: str | None = None,
) -> int:
    """Run the emulator until interrupted; prints the URL to connect to as its first line. ``pendant``: ``-``
    reads pendant commands (:data:`PENDANT`) from stdin, a path reads them from that file; each prints one
    ``pendant: ...`` line, and ``quit`` ends the emulator (so does a program that ends while no pendant can
    restart it). ``options``:
    installed RobotWare option ids, comma-separated (``""``: none; None: :data:`CHANNEL_OPTIONS`). ``op_mode``:
    the key switch (:data:`OP_MODE_NAMES`). ``statement_cost_us``: :data:`STATEMENT_COST_US`. ``pc_address``: the
    TCP build's PC_ADDRESS (None: 127.0.0.1, the local client's). A module the controller would refuse to load
    prints the load error and returns 1."""
    opts = None if options is None else parse_options(options)  # ValueError names an unknown id
    u = urlparse(listen)
    try:
        if u.scheme == "tcp":
            emu = ControllerEmulator(
                "tcp",
                rapid,
                port=u.port or 0,
                faults=fault,
                latency_ms=latency_ms,
                speed_scale=speed_scale,
                options=opts,
                op_mode=op_mode,
                statement_cost_us=statement_cost_us,
                pc_address=pc_address or "127.0.0.1",
            )
        elif u.scheme == "serial":
            if pc_address is not None:
                raise ValueError("pc_address: only the TCP build serves a PC address")
            baud = parse_qs(u.query).get("baudrate")
            emu = ControllerEmulator(
                "serial",
                rapid,
                faults=fault,
                baud=int(baud[0]) if baud else None,
                latency_ms=latency_ms,
                speed_scale=speed_scale,
                options=opts,
                op_mode=op_mode,
                statement_cost_us=statement_cost_us,
            )
        else:
            raise ValueError(
                f"--listen {listen!r}: use tcp://127.0.0.1:PORT (0: any free port) or serial://pty[?baudrate=N]"
            )
    except RapidSyntaxError as e:  # RapidLoadError included: the controller refuses the module
        print(f"RAPID module not loaded: {e}", flush=True)
        return 1
    print(emu.start(), flush=True)
    done = threading.Event()
    if pendant is not None:
        source = sys.stdin if pendant == "-" else Path(pendant).read_text().splitlines()
        threading.Thread(target=run_pendant, args=(emu, source, sys.stdout, done), daemon=True).start()
    try:
        # a stopped program waits for the operator (Ctrl-C ends it); an ended one too while a pendant can restart it
        while emu.thread.is_alive() and not done.is_set() and not (emu.ended and pendant is None):
            emu.thread.join(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    if emu.error is not None:
        print(f"RAPID program stopped: {emu.error}", flush=True)
        return 1
    return 0
