"""Reference re-implementation of the original report's PyBullet action loop (for speed comparisons only).

The original report (a 2020 M.Tech project) drove an ABB IRB 120 in PyBullet with one *action* = one
tool-frame pose increment, executed to convergence before the next action was accepted:

1. read the TCP pose (0.057 m along the gripper frame's x / approach axis);
2. compose it with the action's delta in the tool frame (``multiplyTransforms``);
3. inverse kinematics with ``IK_DLS`` (1000 iterations, residual 1e-5, damping 1e-50) on the
   gripper link, targeting the flange = target TCP moved back 0.057 m along the approach axis;
   on NaN or out-of-limit results a retry with ``IK_SDLS`` plus null-space limits;
4. position control of the 6 arm joints (gain 0.3 / 1.0, max velocity 4 rad/s) and the two
   fingers (0.012 m open, 0.0 closed, force 500);
5. ``stepSimulation`` at 240 Hz until the arm joints are within 1e-4 rad and the fingers within
   1e-3 m of their targets, the robot touches anything but the object, or 5 s of sim time
   (1200 steps) elapsed; in *realtime* mode each step is paced to 1/240 s of wall clock;
6. the episode state: TCP pose, distances, grasp and collision checks via ``getContactPoints``
   and (when rendering) the 84x84 RGB-D hand camera through ``getCameraImage``.

This module rebuilds that loop from the description, with the original report's full scene (plane, table,
yellow source tray, green destination tray, a cube, the robot on a 0.3 m foundation) but with *our*
robot description (``maniskill_irb120.robot.description.urdf_path()``), so the comparison with the
ManiSkill env measures the simulator loop and not two different robot models.

Choices where the description leaves room (documented, none makes PyBullet slower):

- IK end link: ``gripper_base`` (rigidly fixed to ``link6``, i.e. the flange) with the original report's
  0.057 m offset; the TCP pose is read from the URDF's ``tcp`` link, which sits exactly 0.057 m
  along ``gripper_base``'s x axis, so step 1 is the same number the original report computed by hand.
- The URDF's ``tcp`` link is a massless frame (no ``<inertial>``); PyBullet's URDF importer would
  give it the default 1 kg, a payload the original report's gripper did not have, so its mass is set to 1 g.
- The cube is pybullet_data's ``cube_small.urdf`` scaled 0.4 (a 2 cm cube): the gripper opens to
  26 mm, the 5 cm original would not fit.
- The start pose is solved once with PyBullet IK (TCP 0.25 m above the table top between the
  trays, approach axis pointing down) and restored by ``resetJointState`` on every reset.
- Reset (not timed) restores the robot and drops the cube from 5 cm above the source tray floor
  at a random position and orientation, then lets it settle for 0.5 s of sim time.
- An action whose IK result is still out of limits after the SDLS retry is skipped (no motor
  command, no step); the state is still computed (and rendered) like after any action.
"""

from __future__ import annotations

import math
import time

import numpy as np

try:  # pybullet is a dev extra; keep the module importable for docs/linters without it
    import pybullet as p
    import pybullet_data
except ImportError:  # pragma: no cover
    p = None
    pybullet_data = None

TCP_OFFSET = 0.057  # m, TCP along the gripper frame's x (approach) axis
MAX_TRANSLATION = 0.01  # m per action and axis (normalised action 1.0)
MAX_ROTATION = math.radians(10.0)  # rad per action about the approach axis
FINGER_OPEN, FINGER_CLOSED = 0.012, 0.0
SIM_HZ = 240
TIMEOUT_STEPS = 5 * SIM_HZ  # 5 s of sim time
ARM_TOL, FINGER_TOL = 1e-4, 1e-3
IMG_SIZE = 84
CAM_FOV, CAM_NEAR, CAM_FAR = 90.0, 0.001, 2.0
CAM_OFFSET = (-0.03, 0.0, 0.02)  # eye in the TCP frame
TABLE_POS = (0.0, -0.4, 0.0)
SOURCE_TRAY_XY = (0.2, -0.4)
DEST_TRAY_XY = (-0.2, -0.4)
ROBOT_BASE = (0.0, 0.0, 0.3)  # the original report's 0.3 m foundation
START_HEIGHT = 0.25  # TCP above the table top at reset
CUBE_SCALE = 0.4  # cube_small.urdf is 5 cm; 0.4 -> 2 cm
SETTLE_STEPS = SIM_HZ // 2
ARM_JOINTS = tuple(f"joint_{i}" for i in range(1, 7))
FINGER_JOINTS = ("finger_left_joint", "finger_right_joint")
MODES = {  # name -> (render, realtime), the original report's Table 5.1
    "render_realtime": (True, True),
    "render": (True, False),
    "no_render": (False, False),
}


def _require_pybullet():
    if p is None:
        raise ImportError("the PyBullet loop (benchmarks/lib/pybullet_loop.py) needs pybullet (pip install pybullet)")


class SeedPyBulletEnv:
    """The original report's scene and per-action loop in a private PyBullet DIRECT client."""

    def __init__(self, render: bool = True, realtime: bool = False, seed: int = 0):
        _require_pybullet()
        from maniskill_irb120.robot.description import urdf_path

        self.render = render
        self.realtime = realtime
        self.rng = np.random.default_rng(seed)
        self.cid = p.connect(p.DIRECT)
        c = self.cid
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=c)
        p.setGravity(0, 0, -9.81, physicsClientId=c)
        p.setTimeStep(1.0 / SIM_HZ, physicsClientId=c)

        self.plane = p.loadURDF("plane.urdf", physicsClientId=c)
        self.table = p.loadURDF("table/table.urdf", TABLE_POS, globalScaling=0.5, physicsClientId=c)
        self.table_top = p.getAABB(self.table, -1, physicsClientId=c)[1][2]
        self.source_tray = p.loadURDF(
            "tray/traybox.urdf", (*SOURCE_TRAY_XY, self.table_top), globalScaling=0.5, physicsClientId=c
        )
        self.dest_tray = p.loadURDF(
            "tray/traybox.urdf", (*DEST_TRAY_XY, self.table_top), globalScaling=0.5, physicsClientId=c
        )
        p.changeVisualShape(self.source_tray, -1, rgbaColor=(1, 1, 0, 1), physicsClientId=c)
        p.changeVisualShape(self.dest_tray, -1, rgbaColor=(0, 1, 0, 1), physicsClientId=c)
        self.tray_floor = p.getAABB(self.source_tray, -1, physicsClientId=c)[0][2] + 0.01
        self.cube = p.loadURDF(
            "cube_small.urdf", (*SOURCE_TRAY_XY, self.tray_floor + 0.05), globalScaling=CUBE_SCALE, physicsClientId=c
        )
        self.robot = p.loadURDF(urdf_path(), ROBOT_BASE, useFixedBase=True, physicsClientId=c)
        self.bodies = {
            "plane": self.plane,
            "table": self.table,
            "source_tray": self.source_tray,
            "dest_tray": self.dest_tray,
            "cube": self.cube,
            "robot": self.robot,
        }

        # joint / link indices by name; DoF order of calculateInverseKinematics = non-fixed joints
        self.joint_index, self.link_index, self.joint_types = {}, {}, {}
        dof_names, lower, upper = [], [], []
        for j in range(p.getNumJoints(self.robot, physicsClientId=c)):
            info = p.getJointInfo(self.robot, j, physicsClientId=c)
            name, jtype, link = info[1].decode(), info[2], info[12].decode()
            self.joint_index[name], self.link_index[link], self.joint_types[name] = j, j, jtype
            if jtype != p.JOINT_FIXED:
                dof_names.append(name)
                lower.append(info[8])
                upper.append(info[9])
        self.dof_names = dof_names
        self.arm = [self.joint_index[n] for n in ARM_JOINTS]
        self.fingers = [self.joint_index[n] for n in FINGER_JOINTS]
        self.arm_dof = [dof_names.index(n) for n in ARM_JOINTS]
        self.lower, self.upper = np.array(lower), np.array(upper)
        self.arm_lower, self.arm_upper = self.lower[self.arm_dof], self.upper[self.arm_dof]
        self.gripper_link = self.link_index["gripper_base"]
        self.tcp_link = self.link_index["tcp"]
        self.finger_links = [self.link_index["finger_left"], self.link_index["finger_right"]]
        # the URDF's tcp frame has no <inertial>: PyBullet would make it a 1 kg payload
        p.changeDynamics(self.robot, self.tcp_link, mass=1e-3, localInertiaDiagonal=(1e-9,) * 3, physicsClientId=c)
        n = len(dof_names)
        self._ik_dls = dict(
            maxNumIterations=1000, residualThreshold=1e-5, jointDamping=[1e-50] * n, solver=p.IK_DLS, physicsClientId=c
        )
        self._ik_sdls = dict(
            self._ik_dls,
            solver=p.IK_SDLS,
            lowerLimits=list(lower),
            upperLimits=list(upper),
            jointRanges=[2 * math.pi] * n,
            restPoses=[0.0] * n,
        )

        self._proj = p.computeProjectionMatrixFOV(
            fov=CAM_FOV, aspect=1.0, nearVal=CAM_NEAR, farVal=CAM_FAR, physicsClientId=c
        )
        self.q_start = self._solve_start_pose()
        self.finger_target = FINGER_OPEN
        self.n_resets = 0
        self.reset()

    # ------------------------------------------------------------------ helpers
    def close(self) -> None:
        if self.cid is not None and p.isConnected(self.cid):
            p.disconnect(self.cid)
        self.cid = None

    def __del__(self):  # pragma: no cover
        try:
            self.close()
        except Exception:
            pass

    def tcp_pose(self) -> tuple[tuple, tuple]:
        st = p.getLinkState(self.robot, self.tcp_link, computeForwardKinematics=True, physicsClientId=self.cid)
        return st[4], st[5]  # URDF link frame (not the inertial frame)

    def _approach(self, orn) -> np.ndarray:
        return np.asarray(p.getMatrixFromQuaternion(orn, physicsClientId=self.cid)).reshape(3, 3)[:, 0]

    def _set_joints(self, q_arm, finger) -> None:
        for j, q in zip(self.arm, q_arm):
            p.resetJointState(self.robot, j, q, 0.0, physicsClientId=self.cid)
        for j in self.fingers:
            p.resetJointState(self.robot, j, finger, 0.0, physicsClientId=self.cid)

    def _ik(self, tcp_pos, orn) -> np.ndarray | None:
        """Seed step 3: DLS, then SDLS with null-space limits; None when still NaN / out of limits."""
        flange = np.asarray(tcp_pos) - TCP_OFFSET * self._approach(orn)
        for kw in (self._ik_dls, self._ik_sdls):
            q = np.asarray(p.calculateInverseKinematics(self.robot, self.gripper_link, flange.tolist(), orn, **kw))
            q_arm = q[self.arm_dof]
            if np.all(np.isfinite(q_arm)) and np.all(q_arm >= self.arm_lower) and np.all(q_arm <= self.arm_upper):
                return q_arm
        return None

    def _solve_start_pose(self) -> np.ndarray:
        target = np.array([0.0, SOURCE_TRAY_XY[1], self.table_top + START_HEIGHT])
        down = p.getQuaternionFromEuler((0.0, math.pi / 2, 0.0))  # gripper x -> world -z
        q0 = np.array([0.0, 0.3, 0.3, 0.0, 0.9, 0.0])
        q0[0] = math.atan2(target[1], target[0])
        self._set_joints(q0, FINGER_OPEN)
        for _ in range(20):  # IK from the current state, re-seeded with its own result
            q = self._ik(target, down)
            if q is None:
                raise RuntimeError("the original report's start pose is unreachable")
            self._set_joints(q, FINGER_OPEN)
            pos, _ = self.tcp_pose()
            if np.linalg.norm(np.asarray(pos) - target) < 1e-4:
                break
        return q

    def _command(self, q_arm, finger) -> None:
        """Seed step 4."""
        for j, q in zip(self.arm, q_arm):
            p.setJointMotorControl2(
                self.robot,
                j,
                p.POSITION_CONTROL,
                targetPosition=float(q),
                positionGain=0.3,
                velocityGain=1.0,
                maxVelocity=4.0,
                physicsClientId=self.cid,
            )
        p.setJointMotorControlArray(
            self.robot,
            self.fingers,
            p.POSITION_CONTROL,
            targetPositions=[finger] * 2,
            forces=[500] * 2,
            positionGains=[0.3] * 2,
            velocityGains=[1.0] * 2,
            physicsClientId=self.cid,
        )

    def _robot_collided(self) -> bool:
        """The robot touches anything except the object (self-collision is off, as PyBullet's default)."""
        return any(c[2] != self.cube for c in p.getContactPoints(bodyA=self.robot, physicsClientId=self.cid))

    # ------------------------------------------------------------------ episode
    def reset(self) -> dict:
        """Robot to the start pose, fingers open, cube dropped above the source tray (not timed)."""
        c = self.cid
        self._set_joints(self.q_start, FINGER_OPEN)
        self.finger_target = FINGER_OPEN
        self._command(self.q_start, FINGER_OPEN)
        xy = np.asarray(SOURCE_TRAY_XY) + self.rng.uniform(-0.06, 0.06, 2)
        orn = p.getQuaternionFromEuler(self.rng.uniform(-math.pi, math.pi, 3).tolist())
        p.resetBasePositionAndOrientation(self.cube, (*xy, self.tray_floor + 0.05), orn, physicsClientId=c)
        p.resetBaseVelocity(self.cube, (0, 0, 0), (0, 0, 0), physicsClientId=c)
        for _ in range(SETTLE_STEPS):
            p.stepSimulation(physicsClientId=c)
        self.n_resets += 1
        return self.state()

    def act(self, action) -> dict:
        """Execute one normalised action (dx, dy, dz, droll, gripper) to convergence; return the state."""
        c = self.cid
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        # 1-2: current TCP composed with the tool-frame delta
        cur_pos, cur_orn = self.tcp_pose()
        delta_orn = p.getQuaternionFromEuler((float(a[3]) * MAX_ROTATION, 0.0, 0.0))
        tgt_pos, tgt_orn = p.multiplyTransforms(
            cur_pos, cur_orn, (a[:3] * MAX_TRANSLATION).tolist(), delta_orn, physicsClientId=c
        )
        finger = FINGER_OPEN if a[4] > 0 else FINGER_CLOSED
        # 3: IK (DLS, then SDLS)
        q_arm = self._ik(tgt_pos, tgt_orn)
        n_steps, converged, collided = 0, False, False
        if q_arm is not None:
            # 4: motor targets
            self.finger_target = finger
            self._command(q_arm, finger)
            # 5: step to convergence / collision / timeout
            dt = 1.0 / SIM_HZ
            next_t = time.perf_counter()
            while n_steps < TIMEOUT_STEPS:
                p.stepSimulation(physicsClientId=c)
                n_steps += 1
                if self.realtime:
                    next_t += dt
                    sleep = next_t - time.perf_counter()
                    if sleep > 0:
                        time.sleep(sleep)
                if self._robot_collided():
                    collided = True
                    break
                qs = p.getJointStates(self.robot, self.arm + self.fingers, physicsClientId=c)
                q = np.fromiter((s[0] for s in qs), float, len(qs))
                if np.all(np.abs(q[:6] - q_arm) < ARM_TOL) and np.all(np.abs(q[6:] - finger) < FINGER_TOL):
                    converged = True
                    break
        # 6: episode state
        out = self.state(collided=collided)
        out.update(n_substeps=n_steps, converged=converged, skipped=q_arm is None, target_tcp_pos=np.asarray(tgt_pos))
        return out

    def state(self, collided: bool | None = None) -> dict:
        """Seed step 6: poses, distances, grasp / collision checks and the hand camera."""
        c = self.cid
        tcp_pos, tcp_orn = self.tcp_pose()
        tcp_pos = np.asarray(tcp_pos)
        obj_pos, obj_orn = p.getBasePositionAndOrientation(self.cube, physicsClientId=c)
        obj_pos = np.asarray(obj_pos)
        src = np.array([*SOURCE_TRAY_XY, self.tray_floor])
        dst = np.array([*DEST_TRAY_XY, self.tray_floor])
        finger_contacts = [
            len(p.getContactPoints(self.robot, self.cube, linkIndexA=link, physicsClientId=c)) > 0
            for link in self.finger_links
        ]
        obj_touches_other = any(ct[2] != self.robot for ct in p.getContactPoints(bodyA=self.cube, physicsClientId=c))
        grasped = all(finger_contacts) and not obj_touches_other
        if collided is None:
            collided = self._robot_collided()
        out = {
            "tcp_pos": tcp_pos,
            "tcp_orn": np.asarray(tcp_orn),
            "obj_pos": obj_pos,
            "obj_orn": np.asarray(obj_orn),
            "dist_gripper_object": float(np.linalg.norm(tcp_pos - obj_pos)),
            "dist_gripper_source_tray": float(np.linalg.norm(tcp_pos - src)),
            "dist_gripper_dest_tray": float(np.linalg.norm(tcp_pos - dst)),
            "dist_object_dest_tray": float(np.linalg.norm(obj_pos - dst)),
            "finger_contacts": finger_contacts,
            "grasped": bool(grasped),
            "collided": bool(collided),
        }
        if self.render:
            out.update(self.camera(tcp_pos, tcp_orn))
        return out

    def camera(self, tcp_pos, tcp_orn) -> dict:
        """The 84x84 RGB-D hand camera, exactly as the original report called getCameraImage."""
        c = self.cid
        eye, _ = p.multiplyTransforms(tcp_pos, tcp_orn, CAM_OFFSET, (0, 0, 0, 1), physicsClientId=c)
        rot = np.asarray(p.getMatrixFromQuaternion(tcp_orn, physicsClientId=c)).reshape(3, 3)
        eye = np.asarray(eye)
        target = eye + 100.0 * rot[:, 0]
        view = p.computeViewMatrix(eye.tolist(), target.tolist(), rot[:, 2].tolist(), physicsClientId=c)
        # in DIRECT mode PyBullet silently uses its CPU TinyRenderer for ER_BULLET_HARDWARE_OPENGL
        w, h, rgba, depth_buf, _ = p.getCameraImage(
            IMG_SIZE,
            IMG_SIZE,
            view,
            self._proj,
            renderer=p.ER_BULLET_HARDWARE_OPENGL,
            flags=p.ER_NO_SEGMENTATION_MASK,
            physicsClientId=c,
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[:, :, :3]
        zbuf = np.asarray(depth_buf, dtype=np.float32).reshape(h, w)
        depth = CAM_FAR * CAM_NEAR / (CAM_FAR - (CAM_FAR - CAM_NEAR) * zbuf)  # metric depth (m)
        return {"rgb": rgb, "depth": depth}


# --------------------------------------------------------------------------- measurement
def random_actions(n: int, seed: int, dim: int = 5) -> np.ndarray:
    """The benchmark policy for every simulator (sim_speed and pybullet_original): uniform in [-1, 1]^dim;
    for this robot's 5 values the last is the gripper flag (> 0 open)."""
    return np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, dim))


def summarize(times) -> dict:
    t = np.asarray(times, dtype=float)
    q25, q50, q75 = np.percentile(t, [25, 50, 75])
    return {
        "n": int(t.size),
        "mean": float(t.mean()),
        "std": float(t.std()),
        "min": float(t.min()),
        "25%": float(q25),
        "50%": float(q50),
        "75%": float(q75),
        "max": float(t.max()),
        "actions_per_s": float(t.size / t.sum()),
    }


def measure(mode: str, n_actions: int, seed: int = 0) -> dict:
    """Wall time of each ``act`` (rendering per the mode) on seeded random actions, resetting on collision."""
    if mode not in MODES:
        raise ValueError(f"mode={mode!r}: use one of {list(MODES)}")
    render, realtime = MODES[mode]
    env = SeedPyBulletEnv(render=render, realtime=realtime, seed=seed)
    try:
        times, substeps, converged, skipped, collisions = [], [], 0, 0, 0
        for a in random_actions(n_actions, seed):
            t0 = time.perf_counter()
            s = env.act(a)
            times.append(time.perf_counter() - t0)
            substeps.append(s["n_substeps"])
            converged += s["converged"]
            skipped += s["skipped"]
            if s["collided"]:
                collisions += 1
                env.reset()
        stats = summarize(times)
        stats.update(
            mode=mode,
            render=render,
            realtime=realtime,
            seed=seed,
            times=times,
            mean_substeps=float(np.mean(substeps)),
            substeps=substeps,
            n_converged=int(converged),
            n_timeouts=int(sum(1 for n in substeps if n == TIMEOUT_STEPS)),
            n_skipped=int(skipped),
            n_collisions=int(collisions),
            sim_time_per_action=float(np.mean(substeps)) / SIM_HZ,
        )
        return stats
    finally:
        env.close()


def markdown_table(results: list[dict]) -> str:
    head = (
        "| mode | n | mean (s) | std | min | 25% | 50% | 75% | max | actions/s | substeps/action |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    rows = [
        f"| {r['mode']} | {r['n']} | {r['mean']:.4f} | {r['std']:.4f} | {r['min']:.4f} | {r['25%']:.4f} | "
        f"{r['50%']:.4f} | {r['75%']:.4f} | {r['max']:.4f} | {r['actions_per_s']:.2f} | {r['mean_substeps']:.1f} |"
        for r in results
    ]
    return "\n".join([head, *rows])
