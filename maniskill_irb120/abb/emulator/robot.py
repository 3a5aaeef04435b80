"""The IRB 120 behind the controller emulator, what RAPID's motion and kinematics routines act on: joint state
moving over wall-clock time (``clock`` is injectable) in RAPID's units and conventions, with the simulator's own
kinematics, so the emulated robot lands where ``pd_ee_delta_tool`` lands in simulation. How it moves: ``motion.py``;
its simplifications: docs/emulator.md, "Motion".
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import torch

from maniskill_irb120.abb.emulator.confdata import robconf, solve_conf
from maniskill_irb120.abb.emulator.motion import (
    AXIS_ACCEL_TIME_S,
    CORNER_PATH_FAILURE,
    MANUAL_REDUCED_TCP_MM_S,
    NEAR_SINGULARITY,
    QUICK_STOP_DECEL_RATIO,
    STOP_DECEL_RATIO,
    TCP_ACCEL_MM_S2,
    WORLD_ZONE,
    MotionError,
    Phase,
    Segment,
)
from maniskill_irb120.robot.description import urdf_path
from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK, matrix_to_quat, quat_to_matrix

__all__ = ["EmulatedIRB120", "MotionError", "interpolate_pose", "rel_tool"]

# tool0 = flange · R_y(+90°): tool0 z = our flange x (approach), tool0 x = -our flange z
_R_FLANGE_TOOL0 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
# A MoveL's waypoints are 1 mm / 1 deg apart: an axis turning this much between two of them means the line passes
# (within a hair of) a singularity, where an IRC5 stops with 50026. The threshold is an ESTIMATE.
SINGULAR_JUMP_DEG = 20.0
_SAMPLES = 10  # world-zone and TCP-length samples per waypoint interval


class EmulatedIRB120:
    """Joint angles in degrees; poses as 4x4 in metres internally, mm + quaternions at the RAPID boundary.

    ``max_tcp_speed_mm_s``: the TCP speed cap the operating mode imposes (250 in manual reduced speed, the
    default; None in auto), set by the controller. ``events``: (code, title, detail, time) of motion events
    logged (50024). ``motion_error``: the error the robot stopped at while moving, for the controller to stop
    the program with. ``quadrant_tolerance_deg``: None, CalcJointT takes the turn of axes 1, 4, 6 nearest the
    robtarget's quadrant; a number, it refuses a solution further than that outside the quadrant."""

    def __init__(self, q0_deg, clock=time.monotonic):
        self.chain = SerialChain(urdf_path(), "link6", dtype=torch.float64)
        self.ik = SphericalWristIK(self.chain)
        wide = SerialChain(urdf_path(), "link6", dtype=torch.float64)
        wide.lower, wide.upper = wide.lower - 100.0, wide.upper + 100.0
        self.ik_unlimited = SphericalWristIK(wide)  # tells "out of reach" from "breaks a joint limit"
        self.max_speed = np.degrees(self.chain.velocity.numpy())  # ABB's axis speeds, deg/s
        self.max_accel = self.max_speed / AXIS_ACCEL_TIME_S  # deg/s², an estimate (motion.py)
        self.speed_scale = 1.0  # every motion takes 1/speed_scale times its nominal time (a slower robot)
        self.max_tcp_speed_mm_s: float | None = MANUAL_REDUCED_TCP_MM_S
        self.quadrant_tolerance_deg: float | None = None
        self.low, self.high = np.degrees(self.chain.lower.numpy()), np.degrees(self.chain.upper.numpy())
        self.clock = clock
        self.lock = threading.RLock()
        self._q = np.asarray(q0_deg, dtype=np.float64).copy()
        self.queue: list[Segment] = []
        self.stopped = False  # StopMove until StartMove
        self.zone: tuple[np.ndarray, np.ndarray] | None = None  # TCP box (m) the robot may not leave
        self.zone_tool = np.eye(4)
        self.zone_violation = False
        self.events: list[tuple[int | None, str, str, float]] = []  # (code, title, detail, time) for the log
        self.motion_error: MotionError | None = None
        self._t_free = -math.inf  # when the path last came to its end
        self._carry = 0.0  # the fraction of cruise speed the finished segment carries into the next one
        self._stop_ratio = STOP_DECEL_RATIO
        self._planning_since: float | None = None

    # ------------------------------------------------------------------ kinematics (RAPID conventions)
    def tool0(self, q_deg) -> np.ndarray:
        f = self.chain.forward_kinematics(torch.as_tensor(np.radians(q_deg))[None])[0].numpy()
        f[:3, :3] = f[:3, :3] @ _R_FLANGE_TOOL0
        return f

    def tool_pose(self, q_deg, tframe: np.ndarray) -> np.ndarray:
        return self.tool0(q_deg) @ tframe

    def _flange(self, tool_target: np.ndarray, tframe: np.ndarray) -> np.ndarray:
        flange = tool_target @ np.linalg.inv(tframe)
        flange[..., :3, :3] = flange[..., :3, :3] @ _R_FLANGE_TOOL0.T
        return flange

    def solve(self, tool_target: np.ndarray, tframe: np.ndarray, q_ref_deg) -> np.ndarray:
        """Joint angles (deg) putting the tool at ``tool_target`` on ``q_ref``'s branch, or MotionError."""
        flange = torch.as_tensor(self._flange(tool_target, tframe)[None])
        ref = torch.as_tensor(np.radians(np.asarray(q_ref_deg, dtype=np.float64)))[None]
        q, ok = self.ik.solve(flange, ref)
        if bool(ok[0]):
            return np.degrees(q[0].numpy())
        q, ok = self.ik_unlimited.solve(flange, ref)
        if bool(ok[0]):
            raise MotionError(
                "joint_limit", f"the solution {np.round(np.degrees(q[0].numpy()), 2)} deg breaks a joint limit"
            )
        raise MotionError("reach", f"tool position {np.round(tool_target[:3, 3] * 1000, 1)} mm is out of reach")

    def solve_line(self, tool_poses: np.ndarray, tframe: np.ndarray, q_ref_deg) -> tuple[np.ndarray, np.ndarray]:
        """(k, 6) joint angles (deg) for k tool poses along a line, one batched IK call on ``q_ref``'s branch (a
        controller plans a MoveL in well under a millisecond; k single solves took this emulator ~40 ms), and (k,)
        whether each has a solution within the joint limits."""
        seed = torch.as_tensor(np.radians(np.asarray(q_ref_deg, dtype=np.float64))).expand(len(tool_poses), 6)
        q, ok = self.ik.solve(torch.as_tensor(self._flange(tool_poses, tframe)), seed)
        return np.degrees(q.numpy()), ok.numpy()

    def robconf(self, q_deg) -> tuple[int, int, int, int]:
        """ABB's confdata of joint angles (``confdata.robconf``)."""
        return robconf(self.ik, q_deg)

    def solve_conf(self, tool_target: np.ndarray, tframe: np.ndarray, conf) -> np.ndarray:
        """CalcJointT: the joint angles in the robtarget's configuration (``confdata.solve_conf``)."""
        return solve_conf(self, tool_target, self._flange(tool_target, tframe), conf)

    # ------------------------------------------------------------------ motion over wall-clock time
    def joints(self) -> np.ndarray:
        """Current joint angles (deg), advancing the motion queue to now."""
        with self.lock:
            return self._advance(self.clock()).copy()

    def path_end(self) -> np.ndarray:
        """Where the queued path ends (deg): where the next move instruction starts from."""
        with self.lock:
            if self.queue:
                return self.queue[-1].point(self.queue[-1].end_u)
            return self._advance(self.clock()).copy()

    @contextmanager
    def planning(self, t_call: float) -> Iterator[None]:
        """A move instruction reached at ``t_call`` is being planned: the look-ahead counts it as reached then,
        not when the emulator's own IK for it is done (a controller plans a line in well under a millisecond)."""
        self._planning_since = t_call
        try:
            yield
        finally:
            self._planning_since = None

    def busy(self) -> bool:
        """Moving, or with path left to run (not held by StopMove)."""
        with self.lock:
            now = self.clock()
            self._advance(now)
            if not self.queue:
                return False
            head = self.queue[0]
            return not (self.stopped and (not head.phases or now >= head.t_end))

    def move(
        self,
        q_target_deg,
        via=None,
        tframe: np.ndarray | None = None,
        v_tcp: float | None = None,
        v_ori: float | None = None,
        flyby: bool = False,
        t_call: float | None = None,
        error: MotionError | None = None,
        at_end: Callable[[], None] | None = None,
    ) -> None:
        """Queue a segment to ``q_target`` (through ``via`` joint waypoints, e.g. IK along a MoveL's line) at the
        speed the slowest axis, the TCP speed ``v_tcp`` (mm/s, capped by the operating mode) and the reorientation
        speed ``v_ori`` (deg/s) allow; ``flyby``: a zone point, else ``fine``. ``t_call``: when the instruction
        was reached. ``error``: the path ends at ``q_target`` because of it (found by the caller's planning),
        raised when the robot gets there. ``at_end``: called when the robot reaches the segment's end (a fly-by
        point's corner, a stop point), never if the path is cleared or stops at an error before it (MoveLDO's output).
        A target beyond the joint limits is refused now (ERR_ROBLIMIT)."""
        q1 = np.asarray(q_target_deg, dtype=np.float64)
        via = None if via is None or len(via) == 0 else np.asarray(via, dtype=np.float64)
        for q in [q1, *([] if via is None else via)]:
            if np.any(q < self.low - 1e-9) or np.any(q > self.high + 1e-9):
                raise MotionError("joint_limit", f"joint target {np.round(q, 2)} deg breaks a joint limit")
        tframe = self.zone_tool if tframe is None else tframe
        with self.lock:
            now = self.clock() if t_call is None else min(t_call, self.clock())
            q0 = self.path_end()
            pts = np.vstack([q0, *([] if via is None else via), q1])
            frac = np.arange(_SAMPLES) / _SAMPLES
            samples = np.vstack(
                [(pts[:-1, None] + frac[None, :, None] * np.diff(pts, axis=0)[:, None]).reshape(-1, 6), q1]
            )
            f = self.chain.forward_kinematics(torch.as_tensor(np.radians(samples))).numpy()  # one batched FK
            rot = f[:, :3, :3] @ _R_FLANGE_TOOL0 @ tframe[:3, :3]
            tcp = f[:, :3, :3] @ (_R_FLANGE_TOOL0 @ tframe[:3, 3]) + f[:, :3, 3]  # metres
            seg = self._segment(pts, tcp, rot, v_tcp, v_ori, flyby, now)
            seg.error, seg.at_end = error, at_end
            if via is not None:
                self._check_singularity(seg)
            self._check_zone(seg, tcp)
            self.queue.append(seg)

    def _segment(self, pts, tcp, rot, v_tcp, v_ori, flyby, now) -> Segment:
        tcp_mm = float(np.linalg.norm(np.diff(tcp, axis=0), axis=1).sum() * 1000)
        cos = (np.einsum("kij,kij->k", rot[:-1], rot[1:]) - 1) / 2
        ori_deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).sum())
        lq = np.abs(np.diff(pts, axis=0)).sum(0)
        caps = [c for c in (v_tcp, self.max_tcp_speed_mm_s) if c is not None]
        t_nom = max(
            float(np.max(lq / self.max_speed)),
            tcp_mm / min(caps) if caps else 0.0,
            ori_deg / v_ori if v_ori else 0.0,
        )
        s = self.speed_scale
        v = min(s / t_nom, 1e6) if t_nom > 0 else 1e6
        limits = [TCP_ACCEL_MM_S2 / tcp_mm] if tcp_mm > 1e-9 else []
        limits += [float(x) for x in self.max_accel[lq > 1e-9] / lq[lq > 1e-9]]
        a = min(min(limits, default=1e12) * s * s, 1e12)
        return Segment(pts, v, a, flyby, now)

    def _check_singularity(self, seg: Segment) -> None:
        jump = np.abs(np.diff(seg.pts, axis=0)).max(1)
        bad = np.flatnonzero(jump > SINGULAR_JUMP_DEG)
        if bad.size:
            u = bad[0] / (len(seg.pts) - 1)
            if u < seg.end_u:
                seg.end_u = u
                code, title = NEAR_SINGULARITY
                seg.error = MotionError("singularity", f"{title}: the line passes a singularity", code)

    def _check_zone(self, seg: Segment, tcp: np.ndarray) -> None:
        """World-zone supervision: the robot stops at the path's last sample inside the box, when it gets there."""
        if self.zone is None:
            return
        low, high = self.zone
        out = np.flatnonzero(np.any((tcp < low) | (tcp > high), axis=1))
        if out.size == 0:
            return
        u = max(0.0, (out[0] - 1) / (len(tcp) - 1))
        if u < seg.end_u:
            seg.end_u = u
            code, title = WORLD_ZONE
            p = np.round(tcp[out[0]] * 1000, 1)
            seg.error = MotionError("world_zone", f"{title}: the TCP would leave the box at {p} mm", code)

    # the motion queue: each segment starts where the last ended, fly-by or from rest
    def _advance(self, now: float) -> np.ndarray:
        while self.queue:
            seg = self.queue[0]
            if not seg.phases:
                if self._carry == 0 and self.stopped:
                    break
                t0 = self._t_free if self._carry > 0 else max(seg.queued, self._t_free)
                if t0 > now:
                    break
                if self.stopped:  # entered while stopping: it goes on decelerating
                    self._decelerate(seg, t0, 0.0, self._carry * seg.v, has_next=len(self.queue) > 1)
                else:
                    seg.plan(t0, 0.0, self._carry * seg.v, 0.0)
            if not seg.decided:
                self._decide(seg, now)
            if now < seg.t_end:
                self._q = seg.point(seg.u(now))
                break
            u = seg.phases[-1].u(seg.t_end)
            self._q = seg.point(u)
            if u < seg.end_u - 1e-9:  # held on the path by StopMove
                break
            self.queue.pop(0)
            self._t_free, self._carry = seg.t_end, seg.carry
            if seg.error is None and seg.at_end is not None:
                seg.at_end()
            if seg.error is not None:  # found where the robot got to it: it stops there, the program with it
                self.motion_error = seg.error
                self.zone_violation = self.zone_violation or seg.error.kind == "world_zone"
                self.queue.clear()
                self._carry = 0.0
        return self._q

    def _decide(self, seg: Segment, now: float) -> None:
        """The look-ahead rule: a fly-by point is flown by if the next move instruction was reached before the
        robot had to begin decelerating to the point; otherwise it becomes a stop point (50024)."""
        nxt = self.queue[1] if len(self.queue) > 1 else None
        deadline = seg.decel_at
        if seg.flyby and seg.error is None and nxt is not None and nxt.queued <= deadline:
            first = seg.phases[0]
            seg.plan(first.t0, first.u0, first.w0, nxt.max_entry_fraction())
            seg.carry = seg.phases[-1].w(seg.t_end) / seg.v
            seg.decided = True
            return
        pending = self._planning_since is not None and self._planning_since <= deadline
        if nxt is None and (now < deadline or pending):
            return  # the next instruction may still come in time
        seg.decided, seg.carry = True, 0.0
        if seg.flyby and seg.error is None:
            code, title = CORNER_PATH_FAILURE
            why = "no next move instruction" if nxt is None else f"the next one {1000 * (nxt.queued - deadline):.1f} ms"
            self.events.append((code, title, f"fly-by point run as a stop point: {why} in time", deadline))

    def _decelerate(self, seg: Segment, t: float, u: float, w: float, has_next: bool) -> None:
        """Stop on the path from (t, u, w): within this segment, or on into the next if it is flown into."""
        a = seg.a * self._stop_ratio
        rest = seg.end_u - u
        if w * w / (2 * a) <= rest:
            seg.phases, seg.carry = [Phase(t, u, w, -a, t + w / a)], 0.0
        elif has_next and seg.carry > 0:
            w_end = math.sqrt(w * w - 2 * a * rest)
            seg.phases, seg.carry = [Phase(t, u, w, -a, t + (w - w_end) / a)], w_end / seg.v
        elif seg.carry > 0:  # nothing to run on into: the path's end is the stop
            seg.plan(t, u, w, 0.0)
            seg.carry = 0.0
        seg.decided = True

    def wait_done(self, timeout: float = 10.0) -> None:
        deadline = self.clock() + timeout
        while self.busy() and self.clock() < deadline:
            time.sleep(0.002)

    def stop(self, quick: bool = False) -> None:
        """StopMove: decelerate along the path to a stop (faster with \\Quick: StopMove\\Quick, a program halt
        or an emergency stop); StartMove resumes."""
        with self.lock:
            now = self.clock()
            self._advance(now)
            self._stop_ratio = QUICK_STOP_DECEL_RATIO if quick else STOP_DECEL_RATIO
            self.stopped = True
            if self.queue and self.queue[0].phases and now < self.queue[0].t_end:
                seg = self.queue[0]
                self._decelerate(seg, now, seg.u(now), seg.w(now), has_next=len(self.queue) > 1)

    def clear_path(self) -> None:
        """ClearPath: the path not yet run is dropped; the robot stays where it is."""
        with self.lock:
            now = self.clock()
            self._advance(now)
            self.queue.clear()
            self._carry, self._t_free = 0.0, now

    def start(self) -> None:
        """StartMove: the rest of the path, from where the robot was held."""
        with self.lock:
            now = self.clock()
            self._advance(now)
            if not self.stopped:
                return
            self.stopped = False
            self._t_free = max(self._t_free, now)
            if self.queue and self.queue[0].phases:
                seg = self.queue[0]
                seg.decided, seg.carry = False, 0.0
                seg.plan(now, seg.u(now), seg.w(now) if now < seg.t_end else 0.0, 0.0)


def rel_tool(
    target: np.ndarray, dx_mm: float, dy_mm: float, dz_mm: float, rx: float = 0.0, ry: float = 0.0, rz: float = 0.0
) -> np.ndarray:
    """RAPID's RelTool: displaced in the tool frame, then rotated about the tool's x, y, z axes (degrees)."""
    out = target.copy()
    out[:3, 3] = target[:3, 3] + target[:3, :3] @ (np.array([dx_mm, dy_mm, dz_mm]) / 1000)
    for axis, a in ((0, rx), (1, ry), (2, rz)):
        if a:
            c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
            r = np.eye(3)
            i, j = (axis + 1) % 3, (axis + 2) % 3  # cyclic, so each is a right-handed rotation
            r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
            out[:3, :3] = out[:3, :3] @ r
    return out


def interpolate_pose(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """The pose a fraction ``s`` along MoveL's path from ``a`` to ``b``: position on the line, orientation slerped."""
    qa, qb = matrix_to_quat(a[:3, :3]), matrix_to_quat(b[:3, :3])
    if qa @ qb < 0:
        qb = -qb
    theta = math.acos(min(1.0, float(qa @ qb)))
    q = qa if theta < 1e-9 else (math.sin((1 - s) * theta) * qa + math.sin(s * theta) * qb) / math.sin(theta)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = quat_to_matrix(q), a[:3, 3] + s * (b[:3, 3] - a[:3, 3])
    return out
