"""``IRB120RealAgent``: ManiSkill's ``BaseRealAgent`` on an IRB 120 behind our RAPID server (``ABBRobot``).

ManiSkill's ``Sim2RealEnv`` drives it. Two command modes, one action space:

- ``tool_delta`` (default): the env's ``pd_ee_delta_tool`` action goes over the wire as it is, and the
  controller's ``RelTool`` + ``MoveL`` do the rest (the original report's semantics; no sim IK in the loop).
  ``IRB120Sim2RealEnv`` sends it through :meth:`send_tool_action`.
- ``joint_target``: ManiSkill's default path. The sim controller's IK runs on the PC and its joint drive
  targets go out as ``MoveAbsJ`` (:meth:`set_target_qpos`).

The MetalWork gripper is pneumatic with no position feedback: the finger joints in ``qpos`` are the open or
closed stroke the last gripper command selected, unless ``finger_qpos`` (e.g. the digital twin's fingers)
says better.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Literal

import numpy as np
import torch
from mani_skill.agents.base_real_agent import BaseRealAgent

from maniskill_irb120.abb.client import ABBRobot
from maniskill_irb120.abb.protocol import RobotState
from maniskill_irb120.action import gripper_opens
from maniskill_irb120.robot.description import geometry
from maniskill_irb120.robot.irb120 import FINGER_STROKE

CommandMode = Literal["tool_delta", "joint_target"]
COMMAND_MODES = ("tool_delta", "joint_target")
FINGER_CLOSED_HALF_GAP = geometry()["finger_closed_half_gap"]


class IRB120RealAgent(BaseRealAgent):
    """``robot``: a connected ``ABBRobot`` or a URL to connect to on :meth:`start`. ``camera``: any object with
    ``start()``, ``stop()`` and ``read() -> (rgb uint8 (H, W, 3), depth int16 mm (H, W, 1))`` (``RealSenseCamera``,
    ``TwinCamera``), or None for state-only policies."""

    def __init__(
        self,
        robot: ABBRobot | str,
        camera=None,
        command_mode: CommandMode = "tool_delta",
        camera_name: str = "hand_camera",
        finger_qpos: Callable[[], np.ndarray] | None = None,
        sensor_configs: dict | None = None,
    ):
        if command_mode not in COMMAND_MODES:
            raise ValueError(f"command_mode={command_mode!r}: use one of {COMMAND_MODES}")
        super().__init__(sensor_configs or {})
        self._robot_or_url = robot
        self.abb: ABBRobot | None = robot if isinstance(robot, ABBRobot) else None
        self.camera, self.camera_name, self.command_mode = camera, camera_name, command_mode
        self.finger_qpos = finger_qpos
        self.state: RobotState | None = None
        self._step_start: np.ndarray | None = None  # qpos (8,) when the last motion command went out, for qvel
        self._frame: tuple[np.ndarray, np.ndarray] | None = None
        # every exchange with the controller: (kind, t_sent, t_replied, command, joints in the reply, the reply's
        # motion target as position + wxyz), times from time.perf_counter(); what sim2real-eval logs, sysid fits
        self.log: list[tuple[str, float, float, np.ndarray, np.ndarray, np.ndarray]] = []

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self.abb is None:
            self.abb = ABBRobot.connect(self._robot_or_url, timeout=1.0)
        if self.camera is not None:
            self.camera.start()
        self.refresh()

    def stop(self) -> None:
        """Stop the robot and close the link (the controller holds the robot where it is)."""
        if self.camera is not None:
            self.camera.stop()
        if self.abb is not None:
            self.abb.close()

    # ------------------------------------------------------------------ commands
    def refresh(self) -> RobotState:
        """Read the controller's state now (the joints for ``qpos`` and ``qvel``)."""
        t0 = time.perf_counter()
        return self._record(self.abb.state(), "state", t0, np.zeros(0))

    def send_tool_action(self, action) -> RobotState:
        """The env's normalised 5-vector, checked by the client's envelope, executed by the controller."""
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        self._step_start = self.get_qpos()[0].numpy()
        t0 = time.perf_counter()
        return self._record(self.abb.move_tool(a), "tool", t0, a)

    def set_target_qpos(self, qpos) -> None:
        """Sim2RealEnv's path: the sim controller's drive targets (arm 6 + fingers 2) as one ``MoveAbsJ``."""
        q = np.asarray(torch.as_tensor(qpos).detach().cpu(), dtype=np.float64).reshape(-1)
        if q.shape != (8,):
            raise ValueError(f"joint targets are 8 numbers (6 arm joints, 2 fingers), got shape {q.shape}")
        self._step_start = self.get_qpos()[0].numpy()
        t0 = time.perf_counter()
        state = self.abb.move_joints(q[:6], gripper_open=bool(gripper_opens(q[6:].mean() - FINGER_STROKE / 2)))
        self._record(state, "joints", t0, q)

    def set_target_qvel(self, qvel) -> None:
        raise NotImplementedError("the RAPID server takes position targets only; use a pd_*_pos control mode")

    def reset(self, qpos) -> None:
        """Move to ``qpos`` with the controller's reset: one slow joint move, its whole path checked by the
        envelope here and by the RAPID server again, answered once the robot is there; the gripper opens or
        closes as the fingers in ``qpos`` say."""
        q = np.asarray(torch.as_tensor(qpos).detach().cpu(), dtype=np.float64).reshape(-1)
        if q.shape != (8,):
            raise ValueError(f"a reset pose is 8 numbers (6 arm joints, 2 fingers), got shape {q.shape}")
        self.refresh()
        self.abb.reset(q[:6], gripper_open=bool(gripper_opens(q[6:].mean() - FINGER_STROKE / 2)))
        self._step_start = None  # at rest: qvel zero, as the sim's after its reset
        self.refresh()

    # ------------------------------------------------------------------ readings
    def _record(self, state: RobotState, kind: str, t0: float, command: np.ndarray) -> RobotState:
        target = np.r_[state.target_pos, state.target_quat]
        self.log.append((kind, t0, time.perf_counter(), command, np.asarray(state.joints), target))
        self.state = state
        return state

    def get_qpos(self) -> torch.Tensor:
        fingers = self.finger_qpos() if self.finger_qpos is not None else None
        if fingers is None:
            fingers = np.full(2, FINGER_STROKE if self.state.gripper_open else 0.0)
        return torch.as_tensor(np.r_[self.state.joints, fingers], dtype=torch.float32)[None]

    def get_qvel(self) -> torch.Tensor:
        """The sim agent's ``qvel`` (``IRB120Metalwork.step_qvel``): the joints' mean velocity over the last step,
        (qpos now - qpos when the step's command went out) x the control frequency; zero after a reset. The
        protocol carries no speeds, and none are needed: with the step ending where the sim's does (the robot at
        its target), the two sides' displacements agree. The fingers' part is the twin's, or on a real robot the
        jump between the open and the closed stroke (the pneumatic gripper has no position feedback)."""
        if self._step_start is None or self.state is None:
            return torch.zeros(1, 8)
        if self._sim_agent is None:
            raise RuntimeError("qvel is per control period: the sim agent's frequency is needed (Sim2RealEnv sets it)")
        freq = float(self._sim_agent._control_freq)
        return ((self.get_qpos()[0] - torch.as_tensor(self._step_start, dtype=torch.float32)) * freq)[None]

    def get_proprioception(self) -> dict:
        """ManiSkill's (qpos, qvel, controller state) plus the sim agent's ``gripper_opening``, from the fingers."""
        obs = super().get_proprioception()
        obs["gripper_opening"] = obs["qpos"][:, -2:].sum(dim=1, keepdim=True) + 2 * FINGER_CLOSED_HALF_GAP
        return obs

    def capture_sensor_data(self, sensor_names=None) -> None:
        if self.camera is None:
            raise RuntimeError("this real agent has no camera: use a state obs mode or pass camera=...")
        try:
            self._frame = self.camera.read()
        except Exception as e:
            # a policy blind for this step must not act on the last frame: the robot stops first
            if self.abb is not None:
                self.abb.stop()
            raise RuntimeError(f"camera failed ({e}); the robot was stopped") from e

    def own_view(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The hand camera's view of the robot itself from the trained mount: (rgb uint8 (H, W, 3), depth int16 mm
        (H, W, 1), mask (H, W) of the robot's pixels), rendered in the sim at the joints (fingers included) the
        robot last reported, which ``get_info`` synced. What ``MountCorrectedCamera`` draws in."""
        scene = self._sim_agent.scene
        scene.update_render(update_sensors=True, update_human_render_cameras=False)
        cam = scene.sensors[self.camera_name]
        cam.capture()
        obs = cam.get_obs(rgb=True, depth=True, segmentation=True, position=False)
        ids = torch.cat([link.per_scene_id for link in self._sim_agent.robot.get_links()]).cpu()
        mask = torch.isin(obs["segmentation"][0, ..., 0].cpu().long(), ids.long())
        return obs["rgb"][0].cpu().numpy(), obs["depth"][0].cpu().numpy(), mask.numpy()

    def get_sensor_params(self, sensor_names=None) -> dict:
        """The camera's own (the twin renders with known parameters), else the sim camera's at the synced joints:
        the nominal mount and the intrinsics ``to_sim_frame`` produces."""
        if self.camera is None:
            return {}
        params = self.camera.params() if hasattr(self.camera, "params") else None
        if params is None:
            params = self._sim_agent.scene.sensors[self.camera_name].get_params()
        return {self.camera_name: params}

    def get_sensor_data(self, sensor_names=None) -> dict:
        rgb, depth = self._frame
        return {
            self.camera_name: dict(
                rgb=torch.as_tensor(np.ascontiguousarray(rgb))[None],
                depth=torch.as_tensor(np.ascontiguousarray(depth))[None],
            )
        }
