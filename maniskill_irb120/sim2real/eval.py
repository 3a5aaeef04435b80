"""``maniskill-irb120 sim2real-eval``: the same seeds in simulation and through the ABB adapter, side by side.

    maniskill-irb120 sim2real-eval --robot emulator --policy expert --episodes 10 --seed 1000 --out runs/s2r
    maniskill-irb120 sim2real-eval --robot emulator --shift "camera_fov=80,latency=0.02" --policy expert ...
    maniskill-irb120 sim2real-eval --robot tcp://192.168.125.1:5000 --camera realsense --policy CKPT ...

``--robot emulator`` (or ``emulator+serial``) starts the controller emulator running our RAPID module with a
digital twin behind it (the real side's world: ``sim2real/twin.py``); a URL drives a real IRC5, whose episodes the
operator scores at a prompt. Writes ``report.json``, ``report.md`` (+ pictures) and, per real episode, the
exchange log ``logs/real_SEED.npz`` that ``sysid`` fits. Ctrl-C stops the robot and still writes the report.
"""

from __future__ import annotations

import json
import select
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from mani_skill.utils.registration import REGISTERED_ENVS

import maniskill_irb120  # noqa: F401  (registers the tasks)
from maniskill_irb120.envs.randomization import Randomization
from maniskill_irb120.errors import UsageError
from maniskill_irb120.policies.section import read_policy_section, section_sha256
from maniskill_irb120.sim2real.policy import load_policy
from maniskill_irb120.sim2real.sysid import log_arrays

EVENTS = ("success", "grasped", "dropped", "collided")


@dataclass
class EvalConfig:
    robot: str = "emulator"
    """'emulator' (TCP) or 'emulator+serial' (a pty): our RAPID module on the emulator with a digital twin;
    or a controller URL (tcp://HOST:PORT, serial:///dev/ttyUSB0?baudrate=N) for a real IRC5"""
    policy: str = "expert"
    """'expert' (the task's scripted expert; it reads the twin's object pose, so emulator only) or the path
    of an agents.ppo, agents.dagger or agents.sac checkpoint"""
    actions: str = "as-trained"
    """a checkpoint's action: as-trained (as its trainer evaluated it: agents.sac's --eval-deterministic, else
    the mean), mean, or sample (agents.sac/agents.ppo; the noise is seeded by the episode seed, alike on both
    sides)"""
    episodes: int = 10
    seed: int = 1000
    """first seed; episode k runs seed + k on both sides"""
    shift: str | None = None
    """how the twin's world differs from the sim (Randomization.parse syntax, e.g. 'camera_fov=80,light=0.6');
    'latency' goes to the emulator as command latency"""
    sim_shift: bool = False
    """also put the sim side in the --shift's condition: the sim's own prediction of it, which sim-vs-real
    agreement (MMRV, Pearson r) compares with the real side's (what stays out, and why: sim_side_shift)"""
    camera_mount: str | None = None
    """the camera's mount as hand-eye calibration measured it, in the randomisation's words
    ('camera_pos=0.01;-0.01;0.005,camera_rot=3;-3;5'): every frame is reprojected to the mount the policy was
    trained on (MountCorrectedCamera). With --sim-shift the sim side then leaves the mount out of the --shift"""
    env_id: str = "TableClearing-IRB120-v1"
    camera: str = "twin"
    """twin (the twin's render; emulator only), realsense, or none (state-free policies that need no image)"""
    command_mode: str = "tool_delta"
    """tool_delta (the action goes over the wire, RelTool on the controller) or joint_target (sim IK, MoveAbsJ)"""
    step_end: str = "arrived"
    """arrived (a real step ends when the robot stands at its target, as the sim's drives have settled by the end
    of each period) or period (every real step one control period: the robot's own timing, still moving when read)"""
    out: Path = Path("runs/sim2real")
    operator_timeout_s: float = 60.0
    """real robot: seconds to answer 'delivered? [y/n]' after each episode (no answer: scored unknown)"""


def _episode(env, policy, seed: int, real: bool, limit: int) -> dict:
    """One episode; per-step TCP (m, world), joints (rad), actions, events, three hand-camera frames."""
    obs, info = env.reset(seed=seed)
    policy.reset(seed)
    tcp, joints, actions, frames, seen = [], [], [], [], {k: False for k in EVENTS}
    u = env.unwrapped
    for t in range(limit):
        a = policy.act(obs)
        obs, _, term, trunc, info = env.step(a)
        tcp.append((u.tcp_pose[0, :3] if real else u.agent.tcp_pose.p[0]).cpu().numpy().copy())
        joints.append((u.agent.get_qpos() if real else u.agent.robot.get_qpos())[0, :6].cpu().numpy().copy())
        actions.append(np.asarray(torch.as_tensor(a).reshape(-1).cpu()))
        for k in EVENTS:
            seen[k] |= bool(info.get(k, torch.zeros(1))[0])
        if t in (0, 30) and isinstance(obs, dict):
            frames.append(_rgb(obs))
        if bool(term[0]) or bool(trunc[0]):
            break
    if isinstance(obs, dict):
        frames.append(_rgb(obs))
    out = dict(steps=t + 1, success=bool(info["success"][0]), tcp=np.array(tcp), joints=np.array(joints))
    out.update(actions=np.array(actions), frames=frames, **{k: seen[k] for k in EVENTS if k != "success"})
    return out


def _rgb(obs) -> np.ndarray:
    rgb = obs["rgb"] if "rgb" in obs else obs["sensor_data"]["hand_camera"]["rgb"]
    return rgb[0, ..., :3].cpu().numpy().copy()


def _ask_operator(seed: int, timeout: float) -> bool | None:
    print(f"episode seed {seed}: was the object delivered? [y/n] ({timeout:.0f} s) ", end="", flush=True)
    ready, _, _ = select.select([sys.stdin], [], [], timeout)
    if not ready:
        print("(no answer: unknown)")
        return None
    return sys.stdin.readline().strip().lower().startswith("y")


def _deviation(sim: dict, real: dict) -> dict:
    n = min(sim["steps"], real["steps"])
    tcp = np.linalg.norm(sim["tcp"][:n] - real["tcp"][:n], axis=1)
    joint = np.abs(sim["joints"][:n] - real["joints"][:n]).max(axis=1)
    act = np.linalg.norm(sim["actions"][:n] - real["actions"][:n], axis=1)
    return dict(tcp_m=tcp, joint_rad=joint, action=act)


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return {}
    return dict(mean=float(x.mean()), p50=float(np.median(x)), p95=float(np.percentile(x, 95)), max=float(x.max()))


def _parse_shift(spec: str | None):
    """(the twin's randomisation or None, command latency in s for the emulator)."""
    if not spec:
        return None, 0.0
    shift = Randomization.parse(spec)
    latency = float(np.mean(shift.latency)) if shift.latency else 0.0
    return replace(shift, latency=0.0), latency


def sim_side_shift(cfg: EvalConfig) -> Randomization | None:
    """The sim side's model of ``cfg.shift`` with ``--sim-shift`` (None: the nominal task). Two fields stay out:

    - the camera mount, with ``--camera-mount``: the corrected frames come from the trained mount;
    - command latency, with ``step_end="arrived"``: each real step waits until the robot stands at its target,
      so a slow link delays the step but leaves what the policy sees as the latency-free sim's (a 30 ms link moved
      the twin's TCP < 0.5 mm off the sim's over a grasp, ``tests/sim2real``). The sim's ``latency`` (the drives
      get the new targets that far into the period and the arm is read at its end, still moving) models a robot on
      a fixed clock: it goes in with ``step_end="period"``."""
    if not (cfg.sim_shift and cfg.shift):
        return None
    r = Randomization.parse(cfg.shift)
    if cfg.camera_mount:
        r = replace(r, camera_pos=0.0, camera_rot=0.0)
    if cfg.step_end == "arrived":
        r = replace(r, latency=0.0)
    return r if r.active() else None


def _make_real_side(cfg: EvalConfig, sim_env, shift, latency: float):
    """(Sim2RealEnv, agent, twin or None, emulator or None)."""
    from maniskill_irb120.sim2real.agent import IRB120RealAgent
    from maniskill_irb120.sim2real.env import IRB120Sim2RealEnv

    emulator = twin = None
    if cfg.robot.startswith("emulator"):
        from maniskill_irb120.abb.emulator.controller import ControllerEmulator
        from maniskill_irb120.sim2real.twin import DigitalTwin

        channel = "serial" if cfg.robot == "emulator+serial" else "tcp"
        if cfg.robot not in ("emulator", "emulator+serial"):
            raise UsageError(f"--robot {cfg.robot!r}: use emulator, emulator+serial or a controller URL")
        emulator = ControllerEmulator(channel, latency_ms=1000 * latency)
        url = emulator.start()
        twin = DigitalTwin(cfg.env_id, emulator, obs_mode="rgbd", **({"randomization": shift} if shift else {}))
        camera = twin.camera if cfg.camera == "twin" else None
    else:
        url = cfg.robot
        if cfg.camera == "twin":
            raise UsageError("--camera twin needs --robot emulator: a real robot has no twin; use realsense or none")
        if cfg.policy == "expert":
            raise UsageError("--policy expert reads the object's pose, which only the emulator's twin knows")
        camera = None
        if cfg.camera == "realsense":
            from maniskill_irb120.sim2real.cameras import RealSenseCamera

            camera = RealSenseCamera()
    if cfg.camera_mount:
        from maniskill_irb120.sim2real.cameras import MountCorrectedCamera

        camera = MountCorrectedCamera(camera, cfg.camera_mount)
    try:
        agent = IRB120RealAgent(
            url, camera=camera, command_mode=cfg.command_mode, finger_qpos=twin.finger_qpos if twin else None
        )
        env = IRB120Sim2RealEnv(sim_env, agent, world=twin, on_refusal="hold", step_end=cfg.step_end)
        if cfg.camera_mount:
            camera.robot_view = agent.own_view
    except BaseException:  # a refused setting (e.g. --step-end) must not leave the emulator serving
        if emulator is not None:
            emulator.stop()
        if twin is not None:
            twin.close()
        raise
    return env, agent, twin, emulator


def evaluate(cfg: EvalConfig) -> dict:
    from tqdm import tqdm

    from maniskill_irb120.sim2real.report import write_report

    if cfg.sim_shift and not cfg.shift:
        raise UsageError("--sim-shift puts the sim side in the --shift's condition: give a --shift")
    if cfg.camera_mount:  # refused before anything starts
        from maniskill_irb120.sim2real.cameras import parse_mount

        parse_mount(cfg.camera_mount)
        if cfg.camera == "none":
            raise UsageError("--camera-mount corrects a camera's frames: give --camera twin or realsense")
    shift, latency = _parse_shift(cfg.shift)
    sim_shift = sim_side_shift(cfg)
    expert_obs = "state" if cfg.camera == "none" else "rgbd"  # no camera on the real side: none in the sim either
    sim_env, make_policy = load_policy(cfg.policy, cfg.env_id, cfg.command_mode, cfg.actions, sim_shift, expert_obs)
    try:  # the output folder made once the policy was read: a wrong --policy leaves nothing behind
        (cfg.out / "logs").mkdir(parents=True, exist_ok=True)
        real_env, agent, twin, emulator = _make_real_side(cfg, sim_env, shift, latency)
    except BaseException:
        sim_env.close()
        raise
    rows, latencies, interrupted, error, t_start = [], [], False, None, time.time()
    limit = REGISTERED_ENVS[cfg.env_id].max_episode_steps
    bar = tqdm(range(cfg.episodes), desc="sim2real", unit="episode")
    try:
        for k in bar:
            seed = cfg.seed + k
            sim = _episode(sim_env, make_policy(sim_env), seed, False, limit)
            agent.log.clear()
            n_refused, n_late = len(real_env.refusals), real_env.late_steps
            real = _episode(real_env, make_policy(twin.env if twin else real_env), seed, True, limit)
            if twin is None:
                real["success"] = _ask_operator(seed, cfg.operator_timeout_s)
            np.savez(cfg.out / "logs" / f"real_{seed}.npz", **log_arrays(agent.log, real_env.control_dt))
            latencies += [e[2] - e[1] for e in agent.log if e[0] != "state"]
            refused, late = real_env.refusals[n_refused:], real_env.late_steps - n_late
            rows.append(dict(seed=seed, sim=sim, real=real, refused=refused, late=late))
            rows[-1]["deviation"] = _deviation(sim, real)
            bar.set_postfix(
                sim=sum(r["sim"]["success"] for r in rows), real=sum(bool(r["real"]["success"]) for r in rows)
            )
    except KeyboardInterrupt:
        interrupted = True
        print("\ninterrupted: stopping the robot and writing what was measured", file=sys.stderr)
    except Exception as e:  # the report of what was measured is still written, then the error goes on
        error = e
    finally:
        real_env.close()  # the agent stops the robot
        if emulator is not None:
            emulator.stop()
        if twin is not None:
            twin.close()
    shift_dict = dict(shift.as_dict(), latency=latency) if shift else {}
    report = _summarise(cfg, shift_dict, rows, latencies, interrupted, time.time() - t_start)
    report["sim_side"] = sim_shift.as_dict() if sim_shift else None  # the condition the sim side ran in
    report["error"] = None if error is None else f"{type(error).__name__}: {error}"
    write_report(cfg.out, report, rows)
    if error is not None:
        raise error
    return report


def policy_sha256(policy: str) -> str | None:
    """The sha256 of the policy a file holds (``policies.section.section_sha256``: its weights and settings, not the
    file's bytes), which the report keeps so that a finished evaluation is known by the policy it ran, not by a path
    or a file time: a checkpoint and its exported copy are the same policy. None for a policy that is no file
    ('expert')."""
    path = Path(policy)
    return section_sha256(read_policy_section(path)) if path.is_file() else None


def _summarise(cfg: EvalConfig, shift: dict, rows: list, latencies: list, interrupted: bool, wall: float) -> dict:
    def rate(side: str, key: str) -> float | None:
        vals = [r[side][key] for r in rows if r[side][key] is not None]
        return float(np.mean(vals)) if vals else None

    cat = {
        k: np.concatenate([r["deviation"][k] for r in rows]) if rows else np.zeros(0)
        for k in ("tcp_m", "joint_rad", "action")
    }
    refused = [x for r in rows for x in r["refused"]]
    latency = [1000 * x for x in latencies]
    return dict(
        config={k: str(v) for k, v in asdict(cfg).items()},
        policy_sha256=policy_sha256(cfg.policy),
        shift=shift,
        episodes=len(rows),
        interrupted=interrupted,
        wall_clock_s=wall,
        sim={k: rate("sim", k) for k in EVENTS},
        real={k: rate("real", k) for k in EVENTS},
        unscored_real=sum(r["real"]["success"] is None for r in rows),
        mean_steps=dict(
            sim=float(np.mean([r["sim"]["steps"] for r in rows] or [0])),
            real=float(np.mean([r["real"]["steps"] for r in rows] or [0])),
        ),
        deviation=dict(tcp_m=_stats(cat["tcp_m"]), joint_rad=_stats(cat["joint_rad"]), action=_stats(cat["action"])),
        command_latency_ms=_stats(np.array(latency)),
        refused=dict(total=len(refused), by_limit={x: refused.count(x) for x in sorted(set(refused))}),
        late_steps=sum(r["late"] for r in rows),
        per_episode=[
            dict(
                seed=r["seed"],
                sim_success=r["sim"]["success"],
                real_success=r["real"]["success"],
                sim_steps=r["sim"]["steps"],
                real_steps=r["real"]["steps"],
                refused=len(r["refused"]),
            )
            for r in rows
        ],
    )


def main(cfg: EvalConfig) -> int:
    report = evaluate(cfg)
    print(
        json.dumps(
            dict(
                sim_success=report["sim"]["success"],
                real_success=report["real"]["success"],
                episodes=report["episodes"],
                report=str(cfg.out / "report.md"),
            )
        )
    )
    return 1 if report["interrupted"] else 0
