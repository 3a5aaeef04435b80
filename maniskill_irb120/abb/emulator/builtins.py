"""The built-in routines of the emulated IRC5 that act on the robot and the link: kinematics (CRobT, CJointT,
CalcJointT, CalcRobT, RelTool), motion over wall-clock time (MoveL, MoveAbsJ, StopMove, ClearPath, StartMove),
world zones, digital outputs, serial and socket I/O. The language's own built-ins are in ``rapid/stdlib.py``."""

from __future__ import annotations

import functools
import math
import time
from typing import TYPE_CHECKING

import numpy as np

from maniskill_irb120.abb.emulator.rapid import Builtins, RapidError, make_value
from maniskill_irb120.abb.emulator.rapid.stdlib import OP_MODES
from maniskill_irb120.abb.emulator.robot import MotionError, interpolate_pose, rel_tool
from maniskill_irb120.robot.kinematics import matrix_to_quat, pose_mm

if TYPE_CHECKING:
    from maniskill_irb120.abb.emulator.controller import ControllerEmulator


POLL_S = 0.05  # a blocking read or accept looks for a program stop this often

# The key switch: what OpMode() returns in each operating mode (ABB's OpMode: OP_AUTO, OP_MAN_PROG = manual reduced
# speed, TCP at most 250 mm/s with the enabling device held, OP_MAN_TEST = manual full speed)
OP_MODE_NAMES = {"manual_reduced": "OP_MAN_PROG", "auto": "OP_AUTO", "manual_full": "OP_MAN_TEST"}


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


def controller_builtins(self: ControllerEmulator) -> Builtins:
    """The routines an IRC5 provides, acting on ``self``'s robot, signals and link."""
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

    def wait_byte(timeout: float | None) -> int | None:
        """The next byte, or None after ``timeout`` s; the program can be stopped while it waits (on Start
        the wait goes on to its deadline: a read whose \\Time passed while stopped times out at once)."""
        self.interp.settle_time()  # the statements before the read are paid for before it starts waiting
        deadline = time.monotonic() + (8388608.0 if timeout is None else timeout)
        while True:
            b = link.read_byte(min(POLL_S, max(0.0, deadline - time.monotonic())))
            if b is not None or time.monotonic() >= deadline:
                return b
            self.interp.check_stop()

    def write(data: bytes) -> None:
        self.interp.settle_time()
        link.write(data)

    def read_bin(dev, Time=None):
        b = wait_byte(Time)
        if b is None:
            raise RapidError("ERR_DEV_MAXTIME", "ReadBin: no byte within \\Time")
        return b

    reg.add("Open", lambda name, dev, Bin=False, **_: setattr(dev, "value", name))
    reg.add("Close", lambda dev: setattr(dev, "value", None))
    reg.add("ClearIOBuff", lambda dev: link.clear())
    reg.add("ReadBin", io(read_bin))
    reg.add("WriteBin", io(lambda dev, buffer, n: write(bytes(int(b) for b in buffer[: int(n)]))))

    def err_write(header, reason, RL2="", RL3="", RL4="", W=False, I=False):  # noqa: E741
        # the program's own entries: event 80001 (error), 80002 (\W warning), 80003 (\I information)
        text = " | ".join(s for s in (reason, RL2, RL3, RL4) if s)
        self.interp.err_log.append(f"{header} | {text}")
        self.log_event(80003 if I else 80002 if W else 80001, header, text)

    reg.add("ErrWrite", err_write)

    # a socketdev's value is its connection; the link (faults, latency) follows the socketdev last used, so
    # a client can be accepted on a second socketdev while the first one's is still open
    def accept(server, client, Time=None, ClientAddress=None):
        deadline = time.monotonic() + (8388608.0 if Time is None else Time)
        while True:  # in slices: the program can be stopped while it waits for a client
            self._server.settimeout(min(POLL_S, max(0.001, deadline - time.monotonic())))
            try:
                conn, peer = self._server.accept()
                break
            except TimeoutError:
                if time.monotonic() >= deadline:
                    raise RapidError("ERR_SOCK_TIMEOUT", "SocketAccept: no client within \\Time") from None
                self.interp.check_stop()
            except OSError:
                self.interp.check_stop()
                raise
        self._conns.append(conn)
        client.value = conn
        if ClientAddress is not None:
            ClientAddress.set(peer[0])

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
            b = wait_byte(Time)
            if b is None:
                raise RapidError("ERR_SOCK_TIMEOUT", "SocketReceive: no data within \\Time")
            Data.value[i] = b

    reg.add("SocketCreate", lambda sock: None)
    reg.add("SocketBind", lambda sock, address, port: None)  # always the emulator's loopback port
    reg.add("SocketListen", lambda sock: None)
    reg.add("SocketAccept", accept, refs=["ClientAddress"])
    reg.add("SocketReceive", io(receive), refs=["Data"])
    reg.add(
        "SocketSend",
        io(
            lambda sock, Data=None, NoOfBytes=None: (
                use(sock),
                write(bytes(int(b) for b in Data[: int(NoOfBytes or len(Data))])),
            )
        ),
    )
    reg.add("SocketClose", close)
    return reg
