"""Controller emulator: executes our RAPID server (the files users load onto the IRC5) with our RAPID
interpreter, on an emulated IRB 120, serving a pty (serial) or a loopback TCP socket. The modules are the code
under test, loaded as an integrator loads them: the core ``IRB120Server.mod``, the channel module for the link
(``IRB120Serial.mod`` or ``IRB120Socket.mod``) and the world-zone system module ``IRB120Zone.sys``, whose POWER
ON event routine runs before the server's entry routine ``IRB120Server``. What the IRC5 provides to the program
is in ``builtins.py`` (kinematics, motion, world zones, I/O) over ``channel.py`` (the link) and ``robot.py``.

    maniskill-irb120 emulator --listen tcp://127.0.0.1:0      # first line printed: the URL to connect to
"""

from __future__ import annotations

import math
import os
import re
import socket
import threading
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from maniskill_irb120.abb.emulator.builtins import OP_MODE_NAMES, controller_builtins
from maniskill_irb120.abb.emulator.channel import Channel, parse_faults
from maniskill_irb120.abb.emulator.motion import MANUAL_REDUCED_TCP_MM_S
from maniskill_irb120.abb.emulator.pendant import Pendant
from maniskill_irb120.abb.emulator.rapid import (
    Builtins,
    Interpreter,
    RapidStopped,
    RapidSyntaxError,
    parse_options,
)
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
            [*sources, *extra_modules], self._builtins(), options=self.options, statement_cost_s=statement_cost_us / 1e6
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

    def _builtins(self) -> Builtins:
        return controller_builtins(self)


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
) -> int:
    """Run the emulator until interrupted; prints the URL to connect to as its first line. ``options``:
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
    try:
        while emu.thread.is_alive() and not emu.ended:  # a stopped program waits for the operator (Ctrl-C ends it)
            emu.thread.join(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    if emu.error is not None:
        print(f"RAPID program stopped: {emu.error}", flush=True)
        return 1
    return 0
