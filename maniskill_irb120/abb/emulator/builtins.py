"""The routines the emulated IRC5 provides to the program (:data:`CONTROLLER`): kinematics, motion over wall-clock
time, world zones, digital outputs, serial and socket I/O. Registered at module level, as ``rapid/stdlib.py`` registers
the language's own; each reaches the controller running the task as ``interp.host``.
See docs/emulator.md.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable

import numpy as np

from maniskill_irb120.abb.emulator.motion import OUTSIDE_REACH, MotionError
from maniskill_irb120.abb.emulator.rapid import Builtins, Interpreter, RapidError, make_value
from maniskill_irb120.abb.emulator.rapid.stdlib import OP_MODES
from maniskill_irb120.abb.emulator.rapid.values import RawBytes
from maniskill_irb120.abb.emulator.robot import interpolate_pose, rel_tool
from maniskill_irb120.robot.kinematics import matrix_to_quat, pose_mm

POLL_S = 0.05  # a blocking read or accept looks for a program stop this often
WAIT_MAX_S = 8388608.0  # RAPID's WAIT_MAX: wait for ever
DEFAULT_READ_S = 60.0  # a Read* or SocketReceive without \\Time gives up after this (verify)


def _count(n: float, what: str) -> int:
    if not float(n).is_integer() or n < 1:
        raise RapidError("ERR_ARGVALERR", f"{what}:={n}: a whole number of bytes, at least 1")
    return int(n)


# The key switch: what OpMode() returns in each operating mode (ABB's OpMode: OP_AUTO, OP_MAN_PROG = manual reduced
# speed, TCP at most 250 mm/s with the enabling device held, OP_MAN_TEST = manual full speed)
OP_MODE_NAMES = {"manual_reduced": "OP_MAN_PROG", "auto": "OP_AUTO", "manual_full": "OP_MAN_TEST"}


def _pose_of(rt) -> np.ndarray:
    return pose_mm([rt.trans.x, rt.trans.y, rt.trans.z], [rt.rot.q1, rt.rot.q2, rt.rot.q3, rt.rot.q4])


def _tframe(tool) -> np.ndarray:
    f = tool.tframe
    return pose_mm([f.trans.x, f.trans.y, f.trans.z], [f.rot.q1, f.rot.q2, f.rot.q3, f.rot.q4])


def _robtarget(t: np.ndarray, conf=(0, 0, 0, 0)):
    return make_value("robtarget", [list(t[:3, 3] * 1000), list(matrix_to_quat(t[:3, :3])), list(conf), [9e9] * 6])


def _conf(rt) -> tuple[float, float, float, float]:
    c = rt.robconf
    return c.cf1, c.cf4, c.cf6, c.cfx


def _joints(jt) -> np.ndarray:
    r = jt.robax
    return np.array([r.rax_1, r.rax_2, r.rax_3, r.rax_4, r.rax_5, r.rax_6], dtype=np.float64)


CONTROLLER = Builtins()
"""The routines an IRC5 provides to the program. Each routine that acts on the controller takes the interpreter first
(``with_interp``) and reaches the controller that runs the task as ``interp.host``; the Interpreter copies these
entries, so a test may wrap one emulator's routine without touching another's."""


def _reg(name: str, *, refs: tuple[int | str, ...] = (), io: bool = False) -> Callable[[Callable], Callable]:
    """Register ``fn(interp, ...)`` as the controller's RAPID routine ``name``; ``io``: a peer that closed the link
    raises ERR_SOCK_CLOSED."""

    def deco(fn: Callable) -> Callable:
        CONTROLLER.add(name, _io(fn) if io else fn, refs=refs, with_interp=True)
        return fn

    return deco


def _io(fn: Callable) -> Callable:
    @functools.wraps(fn)  # keeps the signature: the registry maps RAPID's option names by it
    def wrapped(*a, **k):
        try:
            return fn(*a, **k)
        except (EOFError, ConnectionError):
            raise RapidError("ERR_SOCK_CLOSED", "peer closed the connection") from None

    return wrapped


# ---- kinematics -------------------------------------------------------------------------------------
def _refusal(e: MotionError) -> RapidError:
    return RapidError("ERR_OUTSIDE_REACH" if e.kind == "reach" else "ERR_ROBLIMIT", str(e))


def _calc_joint_t(robot, rt, tool) -> np.ndarray:
    """CalcJointT honours the robtarget's robconf (RobotWare's ConfL/ConfJ do not change that)."""
    try:
        return robot.solve_conf(_pose_of(rt), _tframe(tool), _conf(rt))
    except MotionError as e:
        raise _refusal(e) from None


@_reg("CJointT")
def _cjointt(interp: Interpreter, **_):
    return make_value("jointtarget", [list(interp.host.robot.joints()), [9e9] * 6])


@_reg("CRobT")
def _crobt(interp: Interpreter, Tool=None, WObj=None):
    robot = interp.host.robot
    q = robot.joints()
    return _robtarget(robot.tool_pose(q, np.eye(4) if Tool is None else _tframe(Tool)), robot.robconf(q))


@_reg("CalcJointT")
def _calcjointt(interp: Interpreter, rt, tool, WObj=None):
    return make_value("jointtarget", [list(_calc_joint_t(interp.host.robot, rt, tool)), [9e9] * 6])


@_reg("CalcRobT")
def _calcrobt(interp: Interpreter, jt, tool, WObj=None):
    robot = interp.host.robot
    return _robtarget(robot.tool_pose(_joints(jt), _tframe(tool)), robot.robconf(_joints(jt)))


# RelTool keeps its input's robconf (ABB, RelTool)
CONTROLLER.add(
    "RelTool",
    lambda rt, dx, dy, dz, Rx=0.0, Ry=0.0, Rz=0.0: _robtarget(
        rel_tool(_pose_of(rt), dx, dy, dz, Rx, Ry, Rz), _conf(rt)
    ),
)


# ---- motion -----------------------------------------------------------------------------------------
def _wait_planned(interp: Interpreter, zone) -> None:
    """The program runs on once the motion is planned: with a fly-by point while the previous segment still
    runs (one segment of look-ahead), with fine once the robot is at the point."""
    robot = interp.host.robot
    while len(robot.queue) > (0 if zone.finep else 1):
        interp.check_stop()
        if robot.motion_error is not None:
            raise robot.motion_error
        robot.wait_done(0.002)


def _move(interp: Interpreter, q, speed, zone, tool, via=None, t_call=None, error=None, at_end=None) -> None:
    emu = interp.host
    robot = emu.robot
    emu.moves += 1
    robot.zone_tool = _tframe(tool)
    try:
        robot.move(q, via, robot.zone_tool, speed.v_tcp, speed.v_ori, not zone.finep, t_call, error, at_end)
    except MotionError as e:
        raise RapidError("ERR_ROBLIMIT", str(e)) from None
    _wait_planned(interp, zone)


def _linear(interp: Interpreter, to, speed, zone, tool, at_end=None) -> None:
    robot = interp.host.robot
    t_call = robot.clock()  # an IRC5 plans the line in its own time: the waypoint IK below is ours
    with robot.planning(t_call):
        tframe = _tframe(tool)
        here, target = robot.tool_pose(robot.path_end(), tframe), _pose_of(to)
        dist = np.linalg.norm(target[:3, 3] - here[:3, 3]) * 1000
        cos = (np.trace(here[:3, :3].T @ target[:3, :3]) - 1) / 2
        angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
        try:
            q1 = robot.solve(target, tframe, robot.path_end())
        except MotionError as e:
            raise _refusal(e) from None
        # a straight line with the orientation turning evenly: IK every millimetre or degree along it
        n = int(min(50, max(1, math.ceil(max(dist, angle)))))
        via, error = [], None
        if n > 1:
            line = np.stack([interpolate_pose(here, target, s) for s in np.arange(1, n) / n])
            via, ok = robot.solve_line(line, tframe, q1)
            if not ok.all():  # met where the robot gets there, not now: it stops at the last point it can reach
                bad = int(np.flatnonzero(~ok)[0])
                code, title = OUTSIDE_REACH
                p = np.round(line[bad, :3, 3] * 1000, 1)
                error = MotionError("reach", f"{title}: no joint solution along the line at {p} mm", code)
                q1, via = (via[bad - 1], via[: bad - 1]) if bad > 0 else (robot.path_end(), [])
        _move(interp, q1, speed, zone, tool, via, t_call, error, at_end)


@_reg("MoveL")
def _move_l(interp: Interpreter, to, speed, zone, tool, WObj=None):
    """MoveL with ConfL\\Off (what the server sets): the line on the current arm branch, robconf ignored."""
    _linear(interp, to, speed, zone, tool)


@_reg("MoveLDO")
def _move_l_do(interp: Interpreter, to, speed, zone, tool, signal, value, WObj=None):
    """MoveLDO: MoveL that sets a digital output in the middle of the corner path of its fly-by point, or at
    its stop point with fine (ABB, MoveLDO; base RAPID, no option), i.e. where the robot reaches the target,
    not when the program pointer passes the instruction as SetDO does (docs/reference.md, look-ahead). A path
    cleared (ClearPath) or stopped at a motion error before the point never sets it (verify)."""
    if value not in (0.0, 1.0):
        raise RapidError("ERR_ARGVALERR", f"MoveLDO: a digital output takes 0 or 1, not {value}")
    v, sig = int(value), interp.host.signals
    _linear(interp, to, speed, zone, tool, at_end=lambda: sig.__setitem__(signal.value, v))


@_reg("MoveAbsJ")
def _move_abs_j(interp: Interpreter, jt, speed, zone, tool, WObj=None):
    """MoveAbsJ: its speeddata holds for the TCP, the reorientation and the axes alike (ABB, MoveAbsJ)."""
    robot = interp.host.robot
    t_call = robot.clock()
    with robot.planning(t_call):
        _move(interp, _joints(jt), speed, zone, tool, None, t_call)


@_reg("StopMove")
def _stop_move(interp: Interpreter, Quick=False, **_):
    """StopMove decelerates along the path; the program goes on once the robot stands still (ClearPath next
    needs the robot stopped)."""
    robot = interp.host.robot
    robot.stop(quick=bool(Quick))
    while robot.busy():
        robot.wait_done(0.002)


@_reg("WaitRob")
def _wait_rob(interp: Interpreter, InPos=False, ZeroSpeed=False):
    """WaitRob \\InPos | \\ZeroSpeed: the program waits until the robot stands still (in position)."""
    robot = interp.host.robot
    while robot.busy():
        interp.check_stop()
        robot.wait_done(0.002)


_reg("ClearPath")(lambda interp: interp.host.robot.clear_path())
_reg("StartMove")(lambda interp, **_: interp.host.robot.start())
CONTROLLER.add("ConfL", lambda **_: None)
CONTROLLER.add("SingArea", lambda **_: None)


# ---- signals, key switch, world zones ---------------------------------------------------------------
CONTROLLER.add("AliasIO", lambda name, signal: setattr(signal, "value", name))
_reg("SetDO")(lambda interp, signal, value: interp.host.signals.__setitem__(signal.value, int(value)))


@_reg("DOutput")
def _d_output(interp: Interpreter, signal):
    interp.host.robot.joints()  # the path up to now has run: an output set along it (MoveLDO) is set
    return interp.host.signals.get(signal.value, 0)


_reg("OpMode")(lambda interp: float(OP_MODES[OP_MODE_NAMES[interp.host.op_mode]]))


@CONTROLLER.register("WZBoxDef")
def _wz_box(shape, low, high, Inside=False, Outside=False):
    shape.value = (np.array([low.x, low.y, low.z]) / 1000, np.array([high.x, high.y, high.z]) / 1000)


_reg("WZLimSup")(lambda interp, zone, shape, Temp=False, Stat=False: setattr(interp.host.robot, "zone", shape.value))


# ---- serial I/O (Open ...\Bin) ----------------------------------------------------------------------
def _wait_bytes(interp: Interpreter, count: int | None, timeout: float, what: str) -> bytes | None:
    """``count`` bytes, or with ``count`` None the first byte and whatever else has already arrived (up to
    RawBytes.MAX); None when they did not all come within ``timeout`` s. The bytes that did come are then
    consumed and lost: what an IRC5 does with a partial read on timeout is not documented where we could read
    it (verify), so the emulator takes the case a server must survive. The program can be stopped while it
    waits (on Start the wait goes on to its deadline: a read whose \\Time passed while stopped times out)."""
    if count is not None and not 1 <= count <= RawBytes.MAX:
        raise RapidError("ERR_ARGVALERR", f"{what}: {count} bytes asked, 1..{RawBytes.MAX} can be read at once")
    link = interp.host.link
    interp.settle_time()  # the statements before the read are paid for before it starts waiting
    deadline = time.monotonic() + timeout
    got = bytearray()
    while count is None or len(got) < count:
        if count is None and got:
            more = link.read_ready(RawBytes.MAX - len(got))
            return bytes(got + more)
        b = link.read_byte(min(POLL_S, max(0.0, deadline - time.monotonic())))
        if b is not None:
            got.append(b)
        elif time.monotonic() >= deadline:
            return None
        else:
            interp.check_stop()
    return bytes(got)


def _opened(dev, what: str) -> None:
    if dev.value is None:
        raise RapidError("ERR_FILEACC", f"{what}: the device is not open (Open ...\\Bin first)")


def _write(interp: Interpreter, data: bytes) -> None:
    interp.settle_time()
    interp.host.link.write(data)


@_reg("ReadBin", io=True)
def _read_bin(interp: Interpreter, dev, Time=None):
    """ReadBin: one byte (without \\Time the emulator waits for ever; the shipped modules always give it)."""
    got = _wait_bytes(interp, 1, WAIT_MAX_S if Time is None else Time, "ReadBin")
    if got is None:
        raise RapidError("ERR_DEV_MAXTIME", "ReadBin: no byte within \\Time")
    return got[0]


@_reg("ReadRawBytes", io=True)
def _read_raw_bytes(interp: Interpreter, dev, RawData: RawBytes, NoOfBytes=None, Time=None):
    """ReadRawBytes IODevice, RawData [\\NoOfBytes] [\\Time] on an ``Open ...\\Bin`` device (base RAPID, no
    option): RawData holds what was read from index 1, its valid length the number read. With \\NoOfBytes
    (1..1024, rawbytes' size) it waits for that many, else for the first and takes what has arrived.
    \\Time (s) expiring raises ERR_DEV_MAXTIME; absent, 60 s (ABB's default for the Read* instructions as
    integrators quote it: verify)."""
    _opened(dev, "ReadRawBytes")
    n = None if NoOfBytes is None else _count(NoOfBytes, "ReadRawBytes \\NoOfBytes")
    got = _wait_bytes(interp, n, DEFAULT_READ_S if Time is None else Time, "ReadRawBytes")
    if got is None:
        raise RapidError("ERR_DEV_MAXTIME", "ReadRawBytes: not all bytes came within \\Time")
    RawData.clear()
    RawData.write(1, got)


@_reg("WriteRawBytes", io=True)
def _write_raw_bytes(interp: Interpreter, dev, RawData: RawBytes, NoOfBytes=None):
    _opened(dev, "WriteRawBytes")
    n = len(RawData) if NoOfBytes is None else _count(NoOfBytes, "WriteRawBytes \\NoOfBytes")
    _write(interp, RawData.read(1, n))


CONTROLLER.add("Open", lambda name, dev, Bin=False, **_: setattr(dev, "value", name))
CONTROLLER.add("Close", lambda dev: setattr(dev, "value", None))
_reg("ClearIOBuff")(lambda interp, dev: interp.host.link.discard_input())
_reg("WriteBin", io=True)(lambda interp, dev, buffer, n: _write(interp, bytes(int(b) for b in buffer[: int(n)])))


@_reg("ErrWrite")
def _err_write(interp: Interpreter, header, reason, RL2="", RL3="", RL4="", W=False, I=False):  # noqa: E741
    # the program's own entries: event 80001 (error), 80002 (\W warning), 80003 (\I information)
    text = " | ".join(s for s in (reason, RL2, RL3, RL4) if s)
    interp.err_log.append(f"{header} | {text}")
    interp.host.log_event(80003 if I else 80002 if W else 80001, header, text)


# ---- sockets (616-1 PC Interface) -------------------------------------------------------------------
# a socketdev's value is its connection; the link (faults, latency) follows the socketdev last used, so
# a client can be accepted on a second socketdev while the first one's is still open
@_reg("SocketAccept", refs=("ClientAddress",))
def _accept(interp: Interpreter, server, client, Time=None, ClientAddress=None):
    emu = interp.host
    deadline = time.monotonic() + (WAIT_MAX_S if Time is None else Time)
    while True:  # in slices: the program can be stopped while it waits for a client
        try:
            conn, peer = emu.accept_client(min(POLL_S, max(0.001, deadline - time.monotonic())))
            break
        except TimeoutError:
            if time.monotonic() >= deadline:
                raise RapidError("ERR_SOCK_TIMEOUT", "SocketAccept: no client within \\Time") from None
            interp.check_stop()
        except OSError:
            interp.check_stop()
            raise
    client.value = conn
    if ClientAddress is not None:
        ClientAddress.set(peer[0])


def _use(link, sock) -> None:
    if sock.value is None:
        raise RapidError("ERR_SOCK_CLOSED", "socket not connected")
    if link.conn is not sock.value:
        link.conn = sock.value
        link.clear()


@_reg("SocketClose")
def _close(interp: Interpreter, sock):
    link = interp.host.link
    if sock.value is not None:
        sock.value.close()
        if link.conn is sock.value:
            link.conn = None
            link.clear()
        sock.value = None


@_reg("SocketReceive", refs=("Str", "Data", "NoRecBytes"), io=True)
def _receive(
    interp: Interpreter, sock, Str=None, RawData=None, Data=None, ReadNoOfBytes=None, NoRecBytes=None, Time=None
):
    """SocketReceive Socket [\\Str] | [\\RawData] | [\\Data] [\\ReadNoOfBytes] [\\NoRecBytes] [\\Time]: exactly
    \\ReadNoOfBytes bytes, else what has arrived (at least one byte; at most 80 characters, 1024 raw bytes or
    the array's size). \\Time (s) expiring raises ERR_SOCK_TIMEOUT; absent, 60 s (verify); a peer that
    closed, ERR_SOCK_CLOSED. The names as open_abb's SERVER.mod and abb_driver's ROS_socket.sys use them."""
    given = [x for x in (Str, RawData, Data) if x is not None]
    if len(given) != 1:
        raise RapidError("ERR_ARGVALERR", "SocketReceive takes one of \\Str, \\RawData or \\Data")
    room = 80 if Str is not None else RawBytes.MAX if RawData is not None else len(Data.value)
    n = None if ReadNoOfBytes is None else _count(ReadNoOfBytes, "SocketReceive \\ReadNoOfBytes")
    if n is not None and n > room:
        raise RapidError("ERR_ARGVALERR", f"SocketReceive \\ReadNoOfBytes:={n}: the receiving data holds {room}")
    _use(interp.host.link, sock)
    got = _wait_bytes(interp, n, DEFAULT_READ_S if Time is None else Time, "SocketReceive")
    if got is None:
        raise RapidError("ERR_SOCK_TIMEOUT", "SocketReceive: not all data came within \\Time")
    got = got[:room]
    if Str is not None:
        Str.value = got.decode("latin-1")
    elif RawData is not None:
        RawData.clear()
        RawData.write(1, got)
    else:
        array = Data.value
        array[: len(got)] = [float(b) for b in got]
        Data.value = array
    if NoRecBytes is not None:
        NoRecBytes.value = float(len(got))


@_reg("SocketSend", io=True)
def _send(interp: Interpreter, sock, Data=None, NoOfBytes=None):
    _use(interp.host.link, sock)
    _write(interp, bytes(int(b) for b in Data[: int(NoOfBytes or len(Data))]))


CONTROLLER.add("SocketCreate", lambda sock: None)
CONTROLLER.add("SocketBind", lambda sock, address, port: None)  # always the emulator's loopback port
CONTROLLER.add("SocketListen", lambda sock: None)
