"""Controller emulator: executes our RAPID server (the files users load onto the IRC5) with our RAPID
interpreter, on an emulated IRB 120, serving a pty (serial) or a loopback TCP socket. The modules are the code
under test, loaded as an integrator loads them: the core ``IRB120Server.mod``, the channel module for the link
(``IRB120Serial.mod`` or ``IRB120Socket.mod``) and the world-zone system module ``IRB120Zone.sys``, whose POWER
ON event routine runs before the server's entry routine ``IRB120Server``. The built-ins here are what an IRC5
provides: kinematics (CRobT, CJointT, CalcJointT, CalcRobT, RelTool), motion over wall-clock time (MoveL,
MoveAbsJ, StopMove, ClearPath, StartMove), world zones, digital outputs, serial and socket I/O.

    maniskill-irb120 emulator --listen tcp://127.0.0.1:0      # first line printed: the URL to connect to
"""

from __future__ import annotations

import functools
import math
import os
import re
import select
import socket
import threading
import time
from collections import deque
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from maniskill_irb120.abb.emulator.rapid import (
    Builtins,
    Interpreter,
    RapidError,
    RapidStopped,
    RapidSyntaxError,
    make_value,
    parse_options,
)
from maniskill_irb120.abb.emulator.rapid.stdlib import OP_MODES
from maniskill_irb120.abb.emulator.robot import EmulatedIRB120, MotionError, interpolate_pose, rel_tool
from maniskill_irb120.robot.irb120 import IRB120Metalwork
from maniskill_irb120.robot.kinematics import matrix_to_quat, pose_mm

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


def server_source(channel: str, rapid: str | Path | None = None, zone: bool = True) -> str:
    """The modules a controller running the server on ``channel`` has loaded, as one source: the core (``rapid``
    instead of the shipped one if given), the channel module and, with ``zone``, the world-zone system module."""
    files = [Path(rapid) if rapid else shipped_module(), rapid_file(CHANNEL_MODULES[channel])]
    if zone:
        files.append(rapid_file("IRB120Zone.sys"))
    return "\n".join(f.read_text() for f in files)


# The default module of a new IRC5 task (what a fresh controller holds before anything is loaded): a second global
# PROC main beside it is an ambiguous name, so a server loaded next to it declares its main LOCAL.
STOCK_MAIN_MODULE = """MODULE MainModule
    PROC main()
        !Add your code here
    ENDPROC
ENDMODULE
"""

# The key switch: what OpMode() returns in each operating mode (ABB's OpMode: OP_AUTO, OP_MAN_PROG = manual reduced
# speed, TCP at most 250 mm/s with the enabling device held, OP_MAN_TEST = manual full speed)
OP_MODE_NAMES = {"manual_reduced": "OP_MAN_PROG", "auto": "OP_AUTO", "manual_full": "OP_MAN_TEST"}

# What each channel's build needs at the least (docs/deploy_irc5.md): serial, nothing (a licence-free controller);
# tcp, the socket API of 616-1 PC Interface (or 672-1 Socket Messaging).
CHANNEL_OPTIONS: dict[str, tuple[str, ...]] = {"serial": (), "tcp": ("616-1",)}


def _pose_of(rt) -> np.ndarray:
    return pose_mm([rt.trans.x, rt.trans.y, rt.trans.z], [rt.rot.q1, rt.rot.q2, rt.rot.q3, rt.rot.q4])


def _tframe(tool) -> np.ndarray:
    f = tool.tframe
    return pose_mm([f.trans.x, f.trans.y, f.trans.z], [f.rot.q1, f.rot.q2, f.rot.q3, f.rot.q4])


def _robtarget(t: np.ndarray):
    return make_value("robtarget", [list(t[:3, 3] * 1000), list(matrix_to_quat(t[:3, :3])), [0, 0, 0, 0], [9e9] * 6])


def _joints(jt) -> np.ndarray:
    r = jt.robax
    return np.array([r.rax_1, r.rax_2, r.rax_3, r.rax_4, r.rax_5, r.rax_6], dtype=np.float64)


FAULTS = ("drop", "corrupt", "dup", "delay", "disconnect", "motors_off", "estop")


def parse_faults(spec: str | None) -> dict[int, tuple[str, float]]:
    """``"drop@2,corrupt@3,dup@4,delay@5:300,disconnect@6,motors_off@7,estop@8"``: what happens to the N-th reply
    the controller sends (1-based). delay takes milliseconds; motors_off and estop set that signal as the reply
    goes out, so the following commands meet it."""
    faults: dict[int, tuple[str, float]] = {}
    for item in filter(None, (spec or "").split(",")):
        m = re.fullmatch(r"(\w+)@(\d+)(?::(\d+(?:\.\d+)?))?", item.strip())
        if not m or m.group(1) not in FAULTS:
            raise ValueError(f"fault {item!r}: use KIND@N[:MS] with KIND one of {FAULTS}, e.g. delay@3:300")
        faults[int(m.group(2))] = (m.group(1), float(m.group(3) or 0))
    return faults


class Channel:
    """The controller's end of the link: a pty master (serial) or an accepted TCP connection; injects
    ``faults`` into the replies it sends (see :func:`parse_faults`). With ``baud`` a serial line's speed is
    emulated (a pty has none): 10 bit times per byte (8N1), each way, one byte after the other. ``latency_s``
    holds every incoming byte back that long (a slow network, a busy controller: the command latency sysid fits)."""

    def __init__(
        self, faults: dict[int, tuple[str, float]], signals: dict[str, int], baud: int | None = None, latency_s=0.0
    ):
        self.fd: int | None = None
        self.conn: socket.socket | None = None
        self.buf: deque[tuple[int, float]] = deque()  # (byte, when its stop bit has arrived)
        self.faults, self.signals, self.replies = faults, signals, 0
        self.byte_s, self.latency_s = (10.0 / baud if baud else 0.0), latency_s
        self._rx_free = 0.0  # when the receive line is free for the next byte

    def read_byte(self, timeout: float) -> int | None:
        if not self.buf:
            src = self.fd if self.conn is None else self.conn
            if src is None or not select.select([src], [], [], max(0.0, timeout))[0]:
                return None
            data = os.read(self.fd, 256) if self.conn is None else self.conn.recv(256)
            if not data:
                raise EOFError("peer closed")
            now = time.monotonic()
            for b in data:
                self._rx_free = max(now + self.latency_s, self._rx_free) + self.byte_s
                self.buf.append((b, self._rx_free))
        b, arrives = self.buf.popleft()
        if (wait := arrives - time.monotonic()) > 0:
            time.sleep(wait)
        return b

    def clear(self) -> None:
        self.buf.clear()

    def write(self, data: bytes) -> None:
        self.replies += 1
        kind, arg = self.faults.get(self.replies, (None, 0.0))
        if kind == "drop":
            return
        if kind == "corrupt":
            data = data[:8] + bytes([data[8] ^ 0x5A]) + data[9:]
        elif kind == "dup":
            data = data + data
        elif kind == "delay":
            time.sleep(arg / 1000)
        elif kind in ("motors_off", "estop"):
            self.signals["doMotorsOn" if kind == "motors_off" else "doEmergencyStop"] = int(kind == "estop")
        elif kind == "disconnect":  # half a frame, then the line goes dead
            self._send(data[: len(data) // 2])
            if self.conn is not None:
                self.conn.shutdown(socket.SHUT_RDWR)
            return
        self._send(data)

    def _send(self, data: bytes) -> None:
        time.sleep(len(data) * self.byte_s)  # the peer has the frame once its last byte is through
        if self.conn is None:
            os.write(self.fd, data)
        else:
            self.conn.sendall(data)


class ControllerEmulator:
    """Runs the server on channel ``serial`` (a pty) or ``tcp`` (127.0.0.1): the core module ``rapid`` (default: the
    shipped one), the shipped channel module for the channel and, with ``zone``, the world-zone system module.

    ``options``: the RobotWare option ids the controller has; None: the least the build needs (serial: none, a
    licence-free controller; tcp: 616-1 PC Interface). The task is refused at load time (:class:`RapidLoadError`)
    if a module names anything of a missing option. ``zone``: load the world-zone system module (None: when
    608-1 World Zones is installed). ``extra_modules``: RAPID texts loaded into the same task (e.g.
    :data:`STOCK_MAIN_MODULE`); ``entry``: the PROC the program starts at (the task's main entry). ``op_mode``:
    the key switch (:data:`OP_MODE_NAMES`), what ``OpMode()`` returns; set :attr:`op_mode` to turn it while the
    program runs."""

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
    ):
        if channel not in CHANNEL_MODULES:
            raise ValueError(f"channel={channel!r}: use 'serial' or 'tcp'")
        self.options = parse_options(CHANNEL_OPTIONS[channel] if options is None else options)
        zone = "608-1" in self.options if zone is None else zone
        self.entry = entry
        if channel not in ("serial", "tcp"):
            raise ValueError(f"channel={channel!r}: use 'serial' or 'tcp'")
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
        source = server_source(channel, rapid, zone)
        self.robot = EmulatedIRB120(q0_deg)
        self.robot.speed_scale = speed_scale
        self.signals = {"doGripperOpen": 1, "doMotorsOn": 1, "doEmergencyStop": 0}
        self.link = Channel(parse_faults(faults), self.signals, baud, latency_ms / 1000)
        self.moves = 0  # motion instructions executed (MoveL, MoveAbsJ): "nothing runs twice" is counted here
        # syntax and load errors (missing options, ambiguous names) surface here, with their module and line
        self.interp = Interpreter([source, *extra_modules], self._builtins(), options=self.options)
        self.error: BaseException | None = None
        self._server: socket.socket | None = None
        self._conns: list[socket.socket] = []  # every client connection accepted (closed by stop())
        self._slave: int | None = None
        self._listening = threading.Event()
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
            self.interp.run(self.entry)
        except RapidStopped:
            pass
        except BaseException as e:  # a fatal program error: the robot stops, as the IRC5 stops the program
            self.robot.stop()
            self.error = e

    def stop(self) -> None:
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

    # ------------------------------------------------------------------ built-ins
    def _builtins(self) -> Builtins:
        reg, robot, sig = Builtins(), self.robot, self.signals

        def io(fn):
            @functools.wraps(fn)  # keeps the signature: the registry maps RAPID's option names by it
            def wrapped(*a, **k):
                try:
                    return fn(*a, **k)
                except (EOFError, ConnectionError):
                    raise RapidError("ERR_SOCK_CLOSED", "peer closed the connection") from None

            return wrapped

        def solve(rt, tool):
            try:
                return robot.solve(_pose_of(rt), _tframe(tool), robot.joints())
            except MotionError as e:
                raise RapidError("ERR_ROBLIMIT" if e.kind == "joint_limit" else "ERR_OUTSIDE_REACH", str(e)) from None

        def move(q, speed, zone, tool, tcp_s=0.0, via=None, t_call=None):
            self.moves += 1
            robot.zone_tool = _tframe(tool)
            try:
                robot.move(q, tool_speed_s=tcp_s, via=via, t_call=t_call)
            except MotionError as e:
                raise RapidError("ERR_ROBLIMIT", str(e)) from None
            if robot.zone_violation:  # world-zone supervision: the IRC5 stops the robot and the program
                robot.stop()
                raise RuntimeError("world zone violated: motion stopped at the zone's boundary")
            while len(robot.queue) > (0 if zone.finep else 1):  # one segment of look-ahead, none with fine
                self.interp.check_stop()
                robot.wait_done(0.002)

        def move_l(to, speed, zone, tool, WObj=None):
            t_call = robot.clock()  # an IRC5 plans the line in its own time: the waypoint IK below is ours
            tframe = _tframe(tool)
            here, target = robot.tool_pose(robot.queue[-1].q1 if robot.queue else robot.joints(), tframe), _pose_of(to)
            dist = np.linalg.norm(target[:3, 3] - here[:3, 3]) * 1000
            cos = (np.trace(here[:3, :3].T @ target[:3, :3]) - 1) / 2
            angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
            q1 = solve(to, tool)
            # a straight line with the orientation turning evenly: IK every millimetre or degree along it
            n = int(min(50, max(1, math.ceil(max(dist, angle)))))
            via = []
            if n > 1:
                line = np.stack([interpolate_pose(here, target, s) for s in np.arange(1, n) / n])
                try:
                    via = robot.solve_line(line, tframe, q1)
                except MotionError as e:
                    raise RapidError("ERR_OUTSIDE_REACH", str(e)) from None
            move(q1, speed, zone, tool, max(dist / speed.v_tcp, angle / speed.v_ori), via, t_call)

        reg.add("CJointT", lambda **_: make_value("jointtarget", [list(robot.joints()), [9e9] * 6]))
        reg.add(
            "CRobT",
            lambda Tool=None, WObj=None: _robtarget(
                robot.tool_pose(robot.joints(), np.eye(4) if Tool is None else _tframe(Tool))
            ),
        )
        reg.add("CalcJointT", lambda rt, tool, WObj=None: make_value("jointtarget", [list(solve(rt, tool)), [9e9] * 6]))
        reg.add("CalcRobT", lambda jt, tool, WObj=None: _robtarget(robot.tool_pose(_joints(jt), _tframe(tool))))
        reg.add(
            "RelTool",
            lambda rt, dx, dy, dz, Rx=0.0, Ry=0.0, Rz=0.0: _robtarget(rel_tool(_pose_of(rt), dx, dy, dz, Rx, Ry, Rz)),
        )
        reg.add("MoveL", move_l)
        reg.add("MoveAbsJ", lambda jt, speed, zone, tool, WObj=None: move(_joints(jt), speed, zone, tool))
        reg.add("StopMove", lambda Quick=False, **_: robot.stop())  # \Quick: the same stop here
        reg.add("ClearPath", lambda: robot.clear_path())
        reg.add("StartMove", lambda **_: robot.start())
        reg.add("ConfL", lambda **_: None)
        reg.add("SingArea", lambda **_: None)
        reg.add("AliasIO", lambda name, signal: setattr(signal, "value", name))
        reg.add("SetDO", lambda signal, value: sig.__setitem__(signal.value, int(value)))
        reg.add("DOutput", lambda signal: sig.get(signal.value, 0))
        reg.add("OpMode", lambda: float(OP_MODES[OP_MODE_NAMES[self.op_mode]]))

        def wz_box(shape, low, high, Inside=False, Outside=False):
            shape.value = (np.array([low.x, low.y, low.z]) / 1000, np.array([high.x, high.y, high.z]) / 1000)

        reg.add("WZBoxDef", wz_box)
        reg.add("WZLimSup", lambda zone, shape, Temp=False, Stat=False: setattr(robot, "zone", shape.value))

        link = self.link

        def read_bin(dev, Time=None):
            b = link.read_byte(8388608.0 if Time is None else Time)
            if b is None:
                raise RapidError("ERR_DEV_MAXTIME", "ReadBin: no byte within \\Time")
            return b

        reg.add("Open", lambda name, dev, Bin=False, **_: setattr(dev, "value", name))
        reg.add("ClearIOBuff", lambda dev: link.clear())
        reg.add("ReadBin", io(read_bin))
        reg.add("WriteBin", io(lambda dev, buffer, n: link.write(bytes(int(b) for b in buffer[: int(n)]))))

        # a socketdev's value is its connection; the link (faults, latency) follows the socketdev last used, so
        # a client can be accepted on a second socketdev while the first one's is still open
        def accept(server, client, Time=None):
            self._server.settimeout(None if Time is None or Time >= 8388608 else Time)
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                raise RapidError("ERR_SOCK_TIMEOUT", "SocketAccept: no client within \\Time") from None
            except OSError:
                self.interp.check_stop()
                raise
            self._conns.append(conn)
            client.value = conn

        def use(sock):
            if sock.value is None:
                raise RapidError("ERR_SOCK_CLOSED", "socket not connected")
            if link.conn is not sock.value:
                link.conn = sock.value
                link.clear()

        def close(sock):
            if sock.value is not None:
                sock.value.close()
                if link.conn is sock.value:
                    link.conn = None
                    link.clear()
                sock.value = None

        def receive(sock, Data=None, ReadNoOfBytes=1, Time=None):
            use(sock)
            for i in range(int(ReadNoOfBytes)):
                b = link.read_byte(8388608.0 if Time is None else Time)
                if b is None:
                    raise RapidError("ERR_SOCK_TIMEOUT", "SocketReceive: no data within \\Time")
                Data.value[i] = b

        reg.add("SocketCreate", lambda sock: None)
        reg.add("SocketBind", lambda sock, address, port: None)  # always the emulator's loopback port
        reg.add("SocketListen", lambda sock: None)
        reg.add("SocketAccept", accept)
        reg.add("SocketReceive", io(receive), refs=["Data"])
        reg.add(
            "SocketSend",
            io(
                lambda sock, Data=None, NoOfBytes=None: (
                    use(sock),
                    link.write(bytes(int(b) for b in Data[: int(NoOfBytes or len(Data))])),
                )
            ),
        )
        reg.add("SocketClose", close)
        return reg


def main(
    listen: str = "tcp://127.0.0.1:0",
    rapid: str | None = None,
    fault: str | None = None,
    latency_ms: float = 0.0,
    speed_scale: float = 1.0,
    options: str | None = None,
    op_mode: str = "manual_reduced",
) -> int:
    """Run the emulator until interrupted; prints the URL to connect to as its first line. ``options``:
    installed RobotWare option ids, comma-separated (``""``: none; None: :data:`CHANNEL_OPTIONS`). ``op_mode``:
    the key switch (:data:`OP_MODE_NAMES`). A module the controller would refuse to load prints the load error
    and returns 1."""
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
            )
        elif u.scheme == "serial":
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
        emu.thread.join()
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()
    if emu.error is not None:
        print(f"RAPID program stopped: {emu.error}", flush=True)
        return 1
    return 0
