"""How the emulated IRB 120 moves a planned path over time: velocity profiles with acceleration limits, fly-by
corners decided by the look-ahead rule (:class:`Segment` ``decide``), stops on the path, and errors met on the
way. Figures that ABB does not publish are estimates, said so where they are defined.
See docs/emulator.md, "Motion".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# ABB IRB 120 data sheet, "Performance": max TCP acceleration 28 m/s², acceleration time 0-1 m/s 0.07 s. The
# path acceleration used here is the second figure, 1 m/s in 0.07 s (14.3 m/s²): an ESTIMATE of what a path
# (not the peak of a joint move) gets; the 28 m/s² peak is not reached along a short linear step.
TCP_ACCEL_MM_S2 = 1000.0 / 0.07
# ESTIMATE: each axis reaches its top speed (250, 250, 250, 320, 320, 420 deg/s) in the same 0.07 s. Axis 1 at
# 250 deg/s in 0.07 s is 62 rad/s², 28 m/s² at a radius of 0.45 m: the data sheet's peak where the arm works.
AXIS_ACCEL_TIME_S = 0.07
# ESTIMATE: StopMove decelerates along the path as a programmed stop point does (ratio 1); StopMove\Quick "stops
# the robot on the path as fast as possible" (ABB, StopMove): taken as twice the path deceleration.
STOP_DECEL_RATIO = 1.0
QUICK_STOP_DECEL_RATIO = 2.0
# Manual reduced speed: the TCP at most 250 mm/s (ABB operating manual; ISO 10218-1 5.6.4); the controller reduces
# the programmed speed rather than refusing it.
MANUAL_REDUCED_TCP_MM_S = 250.0

CORNER_PATH_FAILURE = (50024, "Corner path failure")  # public IRC5 alarm logs; ros-industrial/abb issues 134, 185
OUTSIDE_REACH = (50050, "Position outside reach")  # verified: public RAPID code comments quoting the event
NEAR_SINGULARITY = (50026, "Close to singularity")  # NOT verified in public sources: ABB's number from memory
WORLD_ZONE = (None, "World zone violated")  # ABB's event number for a WZLimSup stop: not found in public sources


class MotionError(RuntimeError):
    """A kinematic failure. ``kind``: reach, joint_limit, config (refused when planned: the RAPID layer turns it
    into its error number) or world_zone, singularity (met while moving: the robot stops there and the controller
    stops the program with it; no RAPID ERROR handler sees it). ``code``: ABB's event number where known."""

    def __init__(self, kind: str, detail: str, code: int | None = None):
        super().__init__(detail)
        self.kind, self.code = kind, code


@dataclass
class Phase:
    """Constant acceleration from (t0, u0, w0) until t1."""

    t0: float
    u0: float
    w0: float
    acc: float
    t1: float

    def u(self, t: float) -> float:
        tau = min(max(t, self.t0), self.t1) - self.t0
        return self.u0 + self.w0 * tau + 0.5 * self.acc * tau * tau

    def w(self, t: float) -> float:
        return self.w0 + self.acc * (min(max(t, self.t0), self.t1) - self.t0)


def trapezoid(t0: float, u0: float, w0: float, u1: float, v: float, a: float, w1: float) -> list[Phase]:
    """From (t0, u0) at speed w0 to u1 at speed w1, no faster than v, accelerating and decelerating at a. A w1 the
    path is too short to reach is lowered; a w0 the path is too short to shed is shed at the end (never planned)."""
    d = u1 - u0
    if d <= 1e-12:
        return [Phase(t0, u1, w0, 0.0, t0)]
    w0 = min(w0, v)
    w1 = min(w1, v, math.sqrt(w0 * w0 + 2 * a * d))
    w1 = max(w1, math.sqrt(max(0.0, w0 * w0 - 2 * a * d)))
    peak = max(min(v, math.sqrt((2 * a * d + w0 * w0 + w1 * w1) / 2)), w0, w1)
    d1, d3 = (peak * peak - w0 * w0) / (2 * a), (peak * peak - w1 * w1) / (2 * a)
    d2 = max(0.0, d - d1 - d3)
    t1 = t0 + (peak - w0) / a
    t2 = t1 + (d2 / peak if peak > 0 else 0.0)
    t3 = t2 + (peak - w1) / a
    return [Phase(t0, u0, w0, a, t1), Phase(t1, u0 + d1, peak, 0.0, t2), Phase(t2, u0 + d1 + d2, peak, -a, t3)]


@dataclass
class Segment:
    """One move instruction's path (joint waypoints at equal spacing of ``u``) and its motion over time."""

    pts: np.ndarray  # (n, 6) joint angles (deg), n >= 2
    v: float  # cruise speed, u/s
    a: float  # acceleration, u/s²
    flyby: bool  # a fly-by point (zone z0..z200) rather than a stop point (fine)
    queued: float  # when the program reached the instruction
    end_u: float = 1.0  # < 1: the path ends early, where ``error`` was found
    error: MotionError | None = None
    phases: list[Phase] = field(default_factory=list)  # empty until the segment starts
    decided: bool = False  # whether its end is known to be a stop or a fly-by
    carry: float = 0.0  # the fraction of cruise speed carried into the next segment (0: a stop point)
    at_end: Callable[[], None] | None = None  # what happens where the robot reaches the end (MoveLDO's output)

    def point(self, u: float) -> np.ndarray:
        x = min(max(u, 0.0), 1.0) * (len(self.pts) - 1)
        i = min(int(x), len(self.pts) - 2)
        return self.pts[i] + (x - i) * (self.pts[i + 1] - self.pts[i])

    def phase(self, t: float) -> Phase:
        return next((p for p in self.phases if t < p.t1), self.phases[-1])

    def u(self, t: float) -> float:
        return self.phase(t).u(t)

    def w(self, t: float) -> float:
        return self.phase(t).w(t) if t < self.phases[-1].t1 else 0.0 if self.carry == 0 else self.phases[-1].w(t)

    @property
    def t_end(self) -> float:
        return self.phases[-1].t1

    @property
    def decel_at(self) -> float:
        """When the deceleration to the segment's end begins: the look-ahead's deadline."""
        return self.phases[-1].t0

    def plan(self, t0: float, u0: float, w0: float, end_fraction: float) -> None:
        self.phases = trapezoid(t0, u0, w0, self.end_u, self.v, self.a, end_fraction * self.v)

    def max_entry_fraction(self) -> float:
        """The largest fraction of cruise speed it may be entered with and still stop at its end (its successor is
        not known yet, so it must be able to)."""
        return min(1.0, math.sqrt(2 * self.a * self.end_u) / self.v)
