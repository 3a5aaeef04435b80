"""ABB's configuration data (``confdata``: cf1, cf4, cf6, cfx) of the emulated IRB 120: what CRobT and CalcRobT
return and what CalcJointT honours. See docs/emulator.md, "Motion".
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import torch

from maniskill_irb120.abb.emulator.motion import MotionError
from maniskill_irb120.robot.kinematics import SphericalWristIK


class Arm(Protocol):
    """What :func:`solve_conf` reads of the robot (``robot.EmulatedIRB120``, which imports this module)."""

    ik: SphericalWristIK  # within the joint limits
    ik_unlimited: SphericalWristIK  # tells "out of reach" from "breaks a joint limit"
    quadrant_tolerance_deg: float | None
    low: np.ndarray  # joint limits, deg
    high: np.ndarray


def robconf(ik: SphericalWristIK, q_deg) -> tuple[int, int, int, int]:
    """ABB's confdata of joint angles: cf1, cf4, cf6 the quadrant of axes 1, 4, 6 (0 for [0, 90) deg, -1 for
    [-90, 0): floor(angle / 90)), cfx the arm and wrist configuration 0-7 = 4 (wrist centre behind axis 1)
    + 2 (wrist centre behind the lower arm) + 1 (axis 5 negative). Source: ABB's confdata description (RAPID
    reference; quoted in CEAD-group/py-opw-kinematics AXIS_CONFIGURATION.md; ROS abb_rapid_msgs RobTarget).
    "Behind the lower arm" is read as the elbow branch past the stretched arm (axis 3 below -77 deg on the
    IRB 120): the table's wording, not checked against a controller."""
    q = np.radians(np.asarray(q_deg, dtype=np.float64))
    beta = ik.phi - q[2]  # the forearm's angle from the stretched elbow (SphericalWristIK's branches)
    reach = ik.a2 * math.sin(q[1]) + ik.L * math.cos(q[1] - beta)  # wrist centre, arm plane x
    cfx = 4 * (reach < 0) + 2 * (math.cos(beta) < 0) + (q[4] < 0)
    c1, c4, c6 = (math.floor(np.degrees(q[i]) / 90.0 + 1e-12) for i in (0, 3, 5))
    return c1, c4, c6, int(cfx)


def solve_conf(robot: Arm, tool_target: np.ndarray, flange: np.ndarray, conf) -> np.ndarray:
    """CalcJointT: the joint angles in the robtarget's configuration ``conf`` (cf1, cf4, cf6, cfx). ABB:
    "The calculation always selects the robot configuration according to the specified configuration data
    in the input robtarget data. Instructions ConfL and ConfJ do not affect this calculation principle"
    (RAPID reference, CalcJointT, as we read it). The arm and wrist branch (cfx) is taken as given; of the
    turns of axes 1, 4, 6, the one nearest the programmed quadrant (not verified: ABB does not say what
    happens to a solution just across a quadrant boundary; ``quadrant_tolerance_deg`` makes it strict).
    ``flange``: the flange pose that puts the tool at ``tool_target``."""
    cf = [int(round(c)) for c in conf]
    cfx = cf[3]
    back, behind, wrist_neg = bool(cfx & 4), bool(cfx & 2), bool(cfx & 1)
    phi = robot.ik.phi
    q3 = phi - math.pi if behind else phi  # beta = pi or 0: the requested elbow branch
    q2 = next(
        a
        for a in (0.0, math.pi / 2, -math.pi / 2, math.pi)
        if (robot.ik.a2 * math.sin(a) + robot.ik.L * math.cos(a - (phi - q3)) < 0) == back
    )
    seed = np.array([0.0, q2, q3, 0.0, -0.5 if wrist_neg else 0.5, 0.0])
    q, ok = robot.ik_unlimited.solve(torch.as_tensor(flange[None]), torch.as_tensor(seed)[None])
    if not bool(ok[0]):
        raise MotionError("reach", f"tool position {np.round(tool_target[:3, 3] * 1000, 1)} mm is out of reach")
    q = np.degrees(q[0].numpy())
    if (q[4] < 0) != wrist_neg and abs(q[4]) > 1e-9:  # the other wrist solution
        q[3], q[4], q[5] = q[3] + 180.0, -q[4], q[5] + 180.0
    for i, c in zip((0, 3, 5), cf[:3], strict=True):  # the turn nearest the programmed quadrant's middle
        q[i] += 360.0 * round((c * 90.0 + 45.0 - q[i]) / 360.0)
        outside = max(c * 90.0 - q[i], q[i] - (c + 1) * 90.0, 0.0)
        if robot.quadrant_tolerance_deg is not None and outside > robot.quadrant_tolerance_deg:
            raise MotionError(
                "config", f"axis {i + 1} at {q[i]:.2f} deg is outside the robtarget's quadrant {c} (robconf {cf})"
            )
    if robconf(robot.ik, q)[3] != cfx:
        raise MotionError("config", f"no solution in configuration cfx {cfx} (robconf {cf})")
    if np.any(q < robot.low - 1e-9) or np.any(q > robot.high + 1e-9):
        raise MotionError("joint_limit", f"the solution {np.round(q, 2)} deg in robconf {cf} breaks a joint limit")
    return q
