"""The safety envelope every command must stay inside before it goes on the wire (the RAPID server checks
the same limits again on the controller: each side holds alone).

Limits: per-step tool motion (the action space's ±1 cm / ±10°), a workspace box for the TCP in the robot base
frame (both trays with margin, never below the table top), ABB's joint limits, and ABB's axis speeds over one
control period. Predictions use the robot's own kinematics (``maniskill_irb120.robot.kinematics``, the same closed
form the simulator's controller uses), so a step the envelope accepts is the step the sim would take.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT, apply_tool_delta
from maniskill_irb120.robot.description import urdf_path
from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK

CONTROL_PERIOD_S = 0.05  # 20 Hz, the env's control rate
# TCP box in the robot base frame (m): both trays (x 0.27..0.43, |y| <= 0.21) with margin, the TCP at least
# 1 cm above the table top, at most 0.45 m high
WORKSPACE_LOW = (0.15, -0.32, 0.01)
WORKSPACE_HIGH = (0.60, 0.32, 0.45)


class EnvelopeError(ValueError):
    """A command outside the envelope; ``limit`` names which: step, workspace, reach, joint_limit, joint_speed."""

    def __init__(self, limit: str, detail: str):
        super().__init__(f"refused by the safety envelope ({limit}): {detail}")
        self.limit, self.detail = limit, detail


@dataclass(frozen=True)
class Envelope:
    workspace_low: tuple[float, float, float] = WORKSPACE_LOW
    workspace_high: tuple[float, float, float] = WORKSPACE_HIGH
    step_pos: float = TOOL_POS_LIMIT
    step_rot: float = TOOL_ROT_LIMIT
    control_period: float = CONTROL_PERIOD_S
    margin: float = 0.001
    """m the TCP keeps inside the box on this side: the PC checks a step from the corners of the path the robot
    may be on (the reply's joints, quantised to 0.02 deg: < 0.3 mm at the TCP; its targets, 0.05 mm), while
    the controller steps from the pose it measures on arrival, somewhere between them (the bow: < 0.1 mm)"""

    def __post_init__(self):
        chain = SerialChain(urdf_path(), "tcp", dtype=torch.float64)
        object.__setattr__(self, "_chain", chain)
        object.__setattr__(self, "_ik", SphericalWristIK(chain))
        object.__setattr__(self, "_max_joint_step", (chain.velocity * self.control_period).numpy())

    @property
    def joint_lower(self) -> np.ndarray:
        return self._chain.lower.numpy()

    @property
    def joint_upper(self) -> np.ndarray:
        return self._chain.upper.numpy()

    def tcp_pose(self, q) -> np.ndarray:
        """(4, 4) TCP pose in the base frame for joint angles ``q`` (6,)."""
        return self._chain.forward_kinematics(torch.as_tensor(np.asarray(q, dtype=np.float64))[None])[0].numpy()

    def check_tool_step(self, q_now, d, rot: float, tcp_now: np.ndarray | None = None) -> np.ndarray:
        """Joint angles (6,) the tool step (``d`` m in the tool frame, then ``rot`` rad about the approach axis)
        leads to from ``q_now``; ``EnvelopeError`` if any limit would be broken. ``tcp_now`` (4x4): the TCP pose
        to step from when it is known better than FK of ``q_now`` (a reply's pose is finer than its joints)."""
        d = np.asarray(d, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or not math.isfinite(rot):
            raise EnvelopeError("step", f"a tool step is 3 finite distances and a finite angle, got {d}, {rot}")
        if np.abs(d).max() > self.step_pos + 1e-12 or abs(rot) > self.step_rot + 1e-12:
            raise EnvelopeError(
                "step",
                f"step {d} m, {math.degrees(rot):.2f} deg exceeds ±{self.step_pos} m per "
                f"axis / ±{math.degrees(self.step_rot):.1f} deg",
            )
        q_now = self._check_joint_vector(q_now, "current joints")
        action = np.concatenate([d, [rot]])[None]
        ref = self.tcp_pose(q_now) if tcp_now is None else np.asarray(tcp_now, dtype=np.float64)
        target = apply_tool_delta(np, ref[None], action)
        self.check_tcp(target[0, :3, 3])
        q, ok = self._ik.solve(torch.as_tensor(target), torch.as_tensor(q_now)[None])
        if not bool(ok[0]):
            raise EnvelopeError("reach", f"no joint solution within ABB's joint limits for TCP {target[0, :3, 3]}")
        q = q[0].numpy()
        self._check_speed(q_now, q)
        return q

    def solve(self, pose: np.ndarray, q_seed) -> np.ndarray:
        """Joint angles (6,) for the TCP ``pose`` (4x4) on ``q_seed``'s branch; ``EnvelopeError`` if none."""
        q, ok = self._ik.solve(
            torch.as_tensor(np.asarray(pose, dtype=np.float64))[None],
            torch.as_tensor(np.asarray(q_seed, dtype=np.float64))[None],
        )
        if not bool(ok[0]):
            raise EnvelopeError("reach", f"no joint solution within ABB's joint limits for TCP {pose[:3, 3]}")
        return q[0].numpy()

    def check_joints(self, q_now, q_target) -> np.ndarray:
        """``q_target`` (6,) if it is within the joint limits, one control period's motion from ``q_now`` at
        ABB's axis speeds, and puts the TCP inside the workspace box; else ``EnvelopeError``."""
        q_now = self._check_joint_vector(q_now, "current joints")
        q_target = self._check_joint_vector(q_target, "joint target")
        low, high = self.joint_lower, self.joint_upper
        bad = np.flatnonzero((q_target < low) | (q_target > high))
        if bad.size:
            i = int(bad[0])
            raise EnvelopeError(
                "joint_limit",
                f"axis {i + 1} target {math.degrees(q_target[i]):.2f} deg is outside "
                f"{math.degrees(low[i]):.1f}..{math.degrees(high[i]):.1f} deg",
            )
        self._check_speed(q_now, q_target)
        self.check_tcp(self.tcp_pose(q_target)[:3, 3])
        return q_target

    def plan_move(self, q_now, q_goal, max_step: np.ndarray) -> list[np.ndarray]:
        """Waypoints (each (6,), the last ``q_goal``) on the straight joint line from ``q_now``: every axis moves
        in proportion, none more than ``max_step`` between two, every TCP inside the box. Planned whole before
        anything moves; ``EnvelopeError`` names the first waypoint outside. (Axes clipped one by one instead
        finish at different times, and that bent path left the box over the top: an episode ending with the
        wrist turned 200 degrees, measured.)"""
        q_now = self._check_joint_vector(q_now, "current joints")
        q_goal = self.check_joints(q_goal, q_goal)
        n = max(1, int(np.ceil((np.abs(q_goal - q_now) / np.asarray(max_step, dtype=np.float64)).max())))
        path = [q_now + (q_goal - q_now) * k / n for k in range(1, n)] + [q_goal]
        for k, q in enumerate(path):
            try:
                self.check_tcp(self.tcp_pose(q)[:3, 3])
            except EnvelopeError as e:
                raise EnvelopeError(
                    "workspace",
                    f"the joint line to {np.round(q_goal, 4)} rad, waypoint {k + 1} of {n}: {e.detail}; "
                    "move the robot nearer first",
                ) from None
        return path

    def move_seconds(self, q_now, q_goal, tcp_m_s: float, ori_rad_s: float, samples: int = 20) -> float:
        """How long a joint move from ``q_now`` to ``q_goal`` takes at a TCP speed and a reorientation speed (and
        ABB's axis speeds): the longest of the three, the TCP's path measured on ``samples`` points of the joint
        line. What the client waits for a reset; acceleration is not in it (the caller adds a margin)."""
        q_now = self._check_joint_vector(q_now, "current joints")
        q_goal = self._check_joint_vector(q_goal, "joint target")
        s = np.linspace(0.0, 1.0, samples + 1)[:, None]
        poses = self._chain.forward_kinematics(torch.as_tensor(q_now + s * (q_goal - q_now))).numpy()
        path = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
        rel = np.einsum("kji,kjl->kil", poses[:-1, :3, :3], poses[1:, :3, :3])
        turn = float(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)).sum())
        axes = float((np.abs(q_goal - q_now) / self._chain.velocity.numpy()).max())
        return max(path / tcp_m_s, turn / ori_rad_s, axes)

    def check_tcp(self, p) -> None:
        p = np.asarray(p, dtype=np.float64)
        low, high = np.asarray(self.workspace_low) + self.margin, np.asarray(self.workspace_high) - self.margin
        if np.any(p < low) or np.any(p > high):
            raise EnvelopeError("workspace", f"TCP {np.round(p, 4)} m is outside the box {low}..{high} m")

    def _check_speed(self, q_now: np.ndarray, q: np.ndarray) -> None:
        over = np.flatnonzero(np.abs(q - q_now) > self._max_joint_step)
        if over.size:
            i = int(over[0])
            raise EnvelopeError(
                "joint_speed",
                f"axis {i + 1} would move {math.degrees(abs(q[i] - q_now[i])):.2f} deg "
                f"in {self.control_period * 1000:.0f} ms, more than ABB's axis speed "
                f"allows ({math.degrees(self._max_joint_step[i]):.2f} deg)",
            )

    @staticmethod
    def _check_joint_vector(q, what: str) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise EnvelopeError("joint_limit", f"{what} must be 6 finite angles (rad), got {q}")
        return q
