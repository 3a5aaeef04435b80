"""``maniskill-irb120 sysid --log DIR``: fit the robot's command latency and speed scaling to what
``sim2real-eval`` logged (``DIR/logs/real_*.npz``: every exchange with the controller, its times, the joints
in each reply and the motion target).

The model is how a position-controlled industrial arm executes our commands: a command sent at ``t`` takes
effect at ``t + latency``; the robot then moves in a straight joint-space line to the target (queued behind
the motion under way, as the RAPID module's look-ahead does), taking ``nominal / speed_scale`` seconds, where
``nominal`` is the time the module's speed data give (``vStep``: 250 mm/s, 250 deg/s; ``MoveAbsJ``: ABB's axis
speeds). Nominal robot: latency 0, speed scale 1. The fit minimises the RMS joint error over every reply.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maniskill_irb120.abb.envelope import Envelope
from maniskill_irb120.errors import MissingFile
from maniskill_irb120.robot.kinematics import pose_mm

V_TCP_M_S = 0.250  # the module's vStep: 250 mm/s along the path, 250 deg/s in orientation
V_ORI_RAD_S = math.radians(250.0)


def log_arrays(log: list, control_dt: float) -> dict:
    """``IRB120RealAgent.log`` as the arrays of one ``real_SEED.npz`` (the file format this module reads)."""
    kinds = np.array([e[0] for e in log])
    width = max((len(e[3]) for e in log), default=0)
    cmds = np.full((len(log), width), np.nan)
    for i, e in enumerate(log):
        cmds[i, : len(e[3])] = e[3]
    return dict(
        kind=kinds,
        t_sent=np.array([e[1] for e in log]),
        t_replied=np.array([e[2] for e in log]),
        command=cmds,
        joints=np.array([e[4] for e in log]).reshape(-1, 6),
        target=np.array([e[5] for e in log]).reshape(-1, 7),
        control_dt=np.array(control_dt),
    )


@dataclass
class Exchanges:
    """One episode's exchanges: send/reply times (s), reply joints (rad), motion commands' target joints."""

    t_sent: np.ndarray  # (n,)
    t_replied: np.ndarray  # (n,)
    joints: np.ndarray  # (n, 6)
    motion: np.ndarray  # (n,) bool: a command that queued a motion
    target: np.ndarray  # (n, 6) joints of the motion target (rows without motion: unused)
    nominal: np.ndarray  # (n,) nominal duration of each motion (s)


def load_log(path: Path, envelope: Envelope | None = None) -> Exchanges:
    env = envelope or Envelope()
    d = np.load(path)
    kind = d["kind"].astype(str)
    joints = d["joints"]
    motion = np.isin(kind, ("tool", "joints"))
    target = joints.copy()
    nominal = np.zeros(len(kind))
    prev_pose, prev_q = env.tcp_pose(joints[0]), joints[0]
    for i in np.flatnonzero(motion):
        pose = pose_mm(d["target"][i, :3] * 1000, d["target"][i, 3:])
        if kind[i] == "joints":
            q = d["command"][i, :6]
            dur = float(np.max(np.abs(q - prev_q) / env._max_joint_step * env.control_period))
        else:
            q = env.solve(pose, joints[i])
            dist = float(np.linalg.norm(pose[:3, 3] - prev_pose[:3, 3]))
            cos = (np.trace(prev_pose[:3, :3].T @ pose[:3, :3]) - 1) / 2
            axes = float(np.max(np.abs(q - prev_q) / env._max_joint_step * env.control_period))  # axis speeds
            dur = max(dist / V_TCP_M_S, math.acos(max(-1.0, min(1.0, cos))) / V_ORI_RAD_S, axes)
        target[i], nominal[i] = q, dur
        prev_pose, prev_q = pose, q
    return Exchanges(d["t_sent"], d["t_replied"], joints, motion, target, nominal)


def predict(ex: Exchanges, latency: float, speed_scale: float) -> np.ndarray:
    """(n, 6) joints the model expects in each reply (read as the reply leaves: ``t_replied``). A fitted
    reply age (joints read earlier than that) traded off against latency and made the fit unstable."""
    idx = np.flatnonzero(ex.motion)
    if idx.size == 0:
        return np.repeat(ex.joints[:1], len(ex.joints), axis=0)
    starts, ends = np.empty(idx.size), np.empty(idx.size)
    t_free = -np.inf
    for k, i in enumerate(idx):  # queued: a motion starts when it arrives or when the one before ends
        starts[k] = max(ex.t_sent[i] + latency, t_free)
        ends[k] = t_free = starts[k] + ex.nominal[i] / speed_scale
    q1 = ex.target[idx]
    q0 = np.vstack([ex.joints[:1], q1[:-1]])
    t = ex.t_replied
    seg = np.searchsorted(starts, t, side="right") - 1
    k = np.clip(seg, 0, None)
    span = np.maximum(ends[k] - starts[k], 1e-9)
    frac = np.clip((t - starts[k]) / span, 0.0, 1.0)[:, None]
    return np.where((seg < 0)[:, None], ex.joints[:1], q0[k] + frac * (q1[k] - q0[k]))


def rms_error(logs: list[Exchanges], latency: float, speed_scale: float) -> float:
    err = np.concatenate([(predict(ex, latency, speed_scale) - ex.joints).ravel() for ex in logs])
    return float(np.sqrt(np.mean(err**2)))


def fit(logs: list[Exchanges]) -> dict:
    """Coarse grid, then finer ones around the best point; returns the fit and the nominal robot's error."""
    lat_grid, scale_grid = np.linspace(0.0, 0.2, 41), np.linspace(0.2, 2.0, 37)
    for _ in range(3):
        errs = np.array([[rms_error(logs, a, b) for b in scale_grid] for a in lat_grid])
        i, j = np.unravel_index(np.argmin(errs), errs.shape)
        lat, scale = lat_grid[i], scale_grid[j]
        dl, ds = (lat_grid[1] - lat_grid[0]), (scale_grid[1] - scale_grid[0])
        lat_grid = np.linspace(max(0.0, lat - dl), lat + dl, 9)
        scale_grid = np.linspace(max(0.05, scale - ds), scale + ds, 9)
    return dict(
        latency_s=float(lat),
        speed_scale=float(scale),
        rms_joint_error_fit_rad=float(errs.min()),
        rms_joint_error_nominal_rad=rms_error(logs, 0.0, 1.0),
        exchanges=int(sum(len(ex.t_sent) for ex in logs)),
        episodes=len(logs),
    )


def excite(agent, steps: int = 60, seed: int = 0, period: float = 0.05) -> None:
    """Drive ``agent`` (a started ``IRB120RealAgent``) with tool steps of random size and direction at 20 Hz,
    reading the state twice a period, so its log separates dead time from slowness. Small steps, inside the
    envelope both sides check; meant for the emulator or a cleared cell at reduced speed."""
    rng = np.random.default_rng(seed)
    for i in range(steps):
        t0 = time.perf_counter()
        size = rng.uniform(0.15, 1.0)
        agent.send_tool_action(np.r_[rng.uniform(-1, 1, 3) * size * (1 if i % 20 < 10 else -1), 0.0, 1.0])
        agent.refresh()
        time.sleep(max(0.0, period - (time.perf_counter() - t0)))
        agent.refresh()


def main(log: str) -> dict:
    root = Path(log)
    files = sorted((root / "logs").glob("real_*.npz")) or sorted(root.glob("real_*.npz"))
    if not files:
        what = "no real_*.npz logs in it or in its logs/" if root.is_dir() else "no such folder"
        raise MissingFile(f"--log {log}: {what}; give the --out folder of a sim2real-eval run")
    result = fit([load_log(f) for f in files])
    (root / "sysid.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result
