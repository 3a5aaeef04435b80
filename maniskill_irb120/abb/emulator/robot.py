"""The IRB 120 behind the controller emulator: what RAPID's motion and kinematics built-ins act on.

Joint state that moves over wall-clock time at ABB's axis speeds, in RAPID's units (mm, degrees, wxyz
quaternions) and conventions: ``tool0`` is the flange with its z axis out of the flange (at the zero pose it
points along base +x), a tool's ``tframe`` is given in ``tool0``. Kinematics are the simulator's own
(``maniskill_irb120.robot.kinematics``), so the emulated robot lands where ``pd_ee_delta_tool`` lands in simulation.

Simplifications, said plainly: a MoveL runs through IK waypoints every millimetre / degree of its straight line
and is joint-interpolated between them; after StopMove + StartMove the rest of a segment is joint-interpolated;
configuration data (``robconf``) is ignored and IK keeps the current arm branch; acceleration is not modelled
(each segment runs at constant joint speed); the world zone is checked on ten points between waypoints.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from maniskill_irb120.robot.description import urdf_path
from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK, matrix_to_quat, quat_to_matrix

# tool0 = flange · R_y(+90°): tool0 z = our flange x (approach), tool0 x = -our flange z
_R_FLANGE_TOOL0 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


class MotionError(RuntimeError):
    """A kinematic failure the RAPID layer turns into its error number (``kind``: reach or joint_limit)."""

    def __init__(self, kind: str, detail: str):
        super().__init__(detail)
        self.kind = kind


@dataclass
class Segment:
    q0: np.ndarray
    q1: np.ndarray
    t0: float
    duration: float
    via: np.ndarray | None = None  # (k, 6) waypoints at equal spacing between q0 and q1 (a MoveL's line)

    def points(self) -> np.ndarray:
        return np.vstack([self.q0, *([] if self.via is None else self.via), self.q1])

    def at(self, t: float) -> np.ndarray:
        s = 1.0 if self.duration <= 0 else min(1.0, max(0.0, (t - self.t0) / self.duration))
        pts = self.points()
        x = s * (len(pts) - 1)
        i = min(int(x), len(pts) - 2)
        return pts[i] + (x - i) * (pts[i + 1] - pts[i])


class EmulatedIRB120:
    """Joint angles in degrees; poses as 4x4 in metres internally, mm + quaternions at the RAPID boundary."""

    def __init__(self, q0_deg, clock=time.monotonic):
        self.chain = SerialChain(urdf_path(), "link6", dtype=torch.float64)
        self.ik = SphericalWristIK(self.chain)
        wide = SerialChain(urdf_path(), "link6", dtype=torch.float64)
        wide.lower, wide.upper = wide.lower - 100.0, wide.upper + 100.0
        self.ik_unlimited = SphericalWristIK(wide)  # tells "out of reach" from "breaks a joint limit"
        self.max_speed = np.degrees(self.chain.velocity.numpy())  # ABB's axis speeds, deg/s
        self.speed_scale = 1.0  # every motion takes 1/speed_scale times its nominal time (a slower robot)
        self.low, self.high = np.degrees(self.chain.lower.numpy()), np.degrees(self.chain.upper.numpy())
        self.clock = clock
        self.lock = threading.Lock()
        self._q = np.asarray(q0_deg, dtype=np.float64).copy()
        self.queue: list[Segment] = []
        self.stopped = False  # StopMove until StartMove
        self.zone: tuple[np.ndarray, np.ndarray] | None = None  # TCP box (m) the robot may not leave
        self.zone_tool = np.eye(4)
        self.zone_violation = False
        self.events: list[tuple[int | None, str, str, float]] = []  # (code, title, detail, time) for the log

    # ------------------------------------------------------------------ kinematics (RAPID conventions)
    def tool0(self, q_deg) -> np.ndarray:
        f = self.chain.forward_kinematics(torch.as_tensor(np.radians(q_deg))[None])[0].numpy()
        f[:3, :3] = f[:3, :3] @ _R_FLANGE_TOOL0
        return f

    def tool_pose(self, q_deg, tframe: np.ndarray) -> np.ndarray:
        return self.tool0(q_deg) @ tframe

    def solve(self, tool_target: np.ndarray, tframe: np.ndarray, q_ref_deg) -> np.ndarray:
        """Joint angles (deg) putting the tool at ``tool_target`` on ``q_ref``'s branch, or MotionError."""
        flange = tool_target @ np.linalg.inv(tframe)
        flange[:3, :3] = flange[:3, :3] @ _R_FLANGE_TOOL0.T
        q, ok = self.ik.solve(torch.as_tensor(flange[None]), torch.as_tensor(np.radians(q_ref_deg))[None])
        if bool(ok[0]):
            return np.degrees(q[0].numpy())
        q, ok = self.ik_unlimited.solve(torch.as_tensor(flange[None]), torch.as_tensor(np.radians(q_ref_deg))[None])
        if bool(ok[0]):
            raise MotionError(
                "joint_limit", f"the solution {np.round(np.degrees(q[0].numpy()), 2)} deg breaks a joint limit"
            )
        raise MotionError("reach", f"tool position {np.round(tool_target[:3, 3] * 1000, 1)} mm is out of reach")

    def solve_line(self, tool_poses: np.ndarray, tframe: np.ndarray, q_ref_deg) -> np.ndarray:
        """(k, 6) joint angles (deg) for k tool poses along a line, one batched IK call on ``q_ref``'s branch (a
        controller plans a MoveL in well under a millisecond; k single solves took this emulator ~40 ms)."""
        flange = tool_poses @ np.linalg.inv(tframe)
        flange[:, :3, :3] = flange[:, :3, :3] @ _R_FLANGE_TOOL0.T
        seed = torch.as_tensor(np.radians(np.asarray(q_ref_deg, dtype=np.float64))).expand(len(flange), 6)
        q, ok = self.ik.solve(torch.as_tensor(flange), seed)
        if not bool(ok.all()):
            bad = int(np.flatnonzero(~ok.numpy())[0])
            raise MotionError(
                "reach", f"no joint solution along the line at {np.round(tool_poses[bad, :3, 3] * 1000, 1)} mm"
            )
        return np.degrees(q.numpy())

    # ------------------------------------------------------------------ motion over wall-clock time
    def joints(self) -> np.ndarray:
        """Current joint angles (deg), advancing the motion queue to now."""
        with self.lock:
            return self._advance(self.clock()).copy()

    def _advance(self, now: float) -> np.ndarray:
        while self.queue and not self.stopped:
            seg = self.queue[0]
            self._q = seg.at(now)
            if now < seg.t0 + seg.duration:
                break
            self.queue.pop(0)
            if self.queue:
                self.queue[0].t0 = seg.t0 + seg.duration
        return self._q

    def busy(self) -> bool:
        with self.lock:
            self._advance(self.clock())
            return bool(self.queue) and not self.stopped

    def move(self, q_target_deg, speed_fraction: float = 1.0, tool_speed_s: float = 0.0, via=None, t_call=None) -> None:
        """Queue a segment to ``q_target`` (through ``via`` joint waypoints, e.g. IK along a MoveL's line): as
        fast as the slowest axis allows at ``speed_fraction`` of ABB's speeds, no faster than ``tool_speed_s``.
        ``t_call``: when the instruction was issued (the emulator's own waypoint IK is not controller time)."""
        q1 = np.asarray(q_target_deg, dtype=np.float64)
        via = None if via is None or len(via) == 0 else np.asarray(via, dtype=np.float64)
        for q in [q1, *([] if via is None else via)]:
            if np.any(q < self.low - 1e-9) or np.any(q > self.high + 1e-9):
                raise MotionError("joint_limit", f"joint target {np.round(q, 2)} deg breaks a joint limit")
        with self.lock:
            now = self.clock() if t_call is None else min(t_call, self.clock())
            q0 = self.queue[-1].q1 if self.queue else self._advance(now).copy()
            seg = Segment(q0, q1, 0.0, 0.0, via)
            pts = seg.points()
            duration = (
                max(
                    float(np.max(np.abs(np.diff(pts, axis=0)).sum(0) / (self.max_speed * speed_fraction))), tool_speed_s
                )
                / self.speed_scale
            )
            seg = self._clip_to_zone(seg)
            seg.t0 = max(now, self.queue[-1].t0 + self.queue[-1].duration) if self.queue else now
            seg.duration = duration
            self.queue.append(seg)

    def _clip_to_zone(self, seg: Segment) -> Segment:
        """World-zone supervision: the segment ends at its last point inside the box (flagging a violation)."""
        if self.zone is None:
            return seg
        low, high = self.zone
        pts = seg.points()
        frac = np.linspace(0.1, 1.0, 10)
        samples = (pts[:-1, None] + frac[None, :, None] * (pts[1:] - pts[:-1])[:, None]).reshape(-1, 6)
        flange = self.chain.forward_kinematics(torch.as_tensor(np.radians(samples)))  # one batched FK
        f = flange.numpy()
        p = f[:, :3, :3] @ (_R_FLANGE_TOOL0 @ self.zone_tool[:3, 3]) + f[:, :3, 3]  # the tool's TCP, in metres
        out = np.flatnonzero(np.any((p < low) | (p > high), axis=1))
        if out.size == 0:
            return seg
        self.zone_violation = True
        kept = [pts[0], *samples[: out[0]]]
        return Segment(kept[0], kept[-1], 0.0, 0.0, np.asarray(kept[1:-1]) if len(kept) > 2 else None)

    def wait_done(self, timeout: float = 10.0) -> None:
        deadline = self.clock() + timeout
        while self.busy() and self.clock() < deadline:
            time.sleep(0.002)

    def stop(self, quick: bool = False) -> None:
        """StopMove (``quick``: StopMove\\Quick, a program halt or an emergency stop): freeze where the robot is."""
        with self.lock:
            self._advance(self.clock())
            self.stopped = True

    def clear_path(self) -> None:
        with self.lock:
            self.queue.clear()

    def start(self) -> None:
        with self.lock:
            if self.stopped and self.queue:
                self.queue[0] = Segment(self._q.copy(), self.queue[0].q1, self.clock(), self.queue[0].duration)
            self.stopped = False


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
