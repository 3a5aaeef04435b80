"""Controllers for the original report's action space (``maniskill_irb120.action``).

ManiSkill's ``PDEEPoseController`` only takes root-frame deltas on the GPU, while the original report acts in
the tool frame: δx, δy, δz along the TCP axes and a rotation about the approach axis (TCP +x).
``PDEEDeltaToolController`` composes the tool-frame delta itself and solves inverse kinematics in
batched torch, so one code path serves ``physx_cpu`` (num_envs=1) and ``physx_cuda`` (num_envs=N):
in closed form for the IRB 120's spherical wrist (exact, one pass), or by damped least squares for
any other serial chain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Union

import numpy as np
import torch
from gymnasium import spaces
from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController, PDEEPoseControllerConfig
from mani_skill.agents.controllers.pd_joint_pos import PDJointPosController, PDJointPosControllerConfig
from mani_skill.utils.geometry.rotation_conversions import quaternion_to_matrix
from mani_skill.utils.structs.types import Array

from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT, gripper_opens, scale_tool_action
from maniskill_irb120.maniskill_compat import PartialResetControllerMixin, set_drive_targets, true_reset_mask
from maniskill_irb120.robot.kinematics import ArmIK, DLSParams, SerialChain, matrix_to_quaternion


def _pose_matrix(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    m = torch.zeros(p.shape[0], 4, 4, device=p.device, dtype=p.dtype)
    m[:, :3, :3] = quaternion_to_matrix(q)
    m[:, :3, 3] = p
    m[:, 3, 3] = 1
    return m


class PDEEDeltaToolController(PDJointPosController):
    """Tool-frame delta pose controller: [δx, δy, δz, δθ] with δθ about the approach axis (TCP x).

    Normalised actions in [-1, 1] are clipped to that box, then scaled to ±``pos_limit`` metres
    and ±``rot_limit`` radians. The new TCP target is ``T_ref · Δ`` with ``T_ref`` the current TCP
    pose (or the last target with ``use_target``) and ``Δ`` the translation followed by the rotation,
    both in the tool frame (the original report's ``multiplyTransforms(current, delta)``). A target that IK
    cannot reach within tolerance (outside the workspace or joint limits) is not applied: that env
    keeps its last reachable joint target and ``ik_unreachable`` is set for it. So is a target that
    would need a joint to move faster than its URDF velocity limit (ABB's axis speeds) within one
    control period: such jumps happen only at singularities, and a real arm could not follow them.
    """

    config: PDEEDeltaToolControllerConfig

    def _initialize_joints(self):
        super()._initialize_joints()
        c = self.config
        self.chain = SerialChain(c.urdf_path, c.ee_link, device=self.device)
        if self.chain.joint_names != list(c.joint_names):
            raise ValueError(f"IK chain joints {self.chain.joint_names} differ from controller joints {c.joint_names}")
        self.ik = ArmIK(
            self.chain,
            c.ik_solver,
            DLSParams(c.ik_iterations, c.ik_damping, c.ik_pos_tol, c.ik_rot_tol),
            max_joint_step=self.chain.velocity / self._control_freq,
        )
        self.ee_link = self.articulation.links_map[c.ee_link]
        self.root_link = self.articulation.root
        self.ik_unreachable = torch.zeros(self.scene.num_envs, dtype=torch.bool, device=self.device)
        self._target_pose = None

    def _initialize_action_space(self):
        c = self.config
        high = np.array([c.pos_limit] * 3 + [c.rot_limit], dtype=np.float32)
        self.single_action_space = spaces.Box(-high, high, dtype=np.float32)

    def _clip_and_scale_action(self, action):
        return scale_tool_action(action, self.config.pos_limit, self.config.rot_limit)

    def ee_pose_at_base(self) -> torch.Tensor:
        """Current TCP pose in the robot root frame as (N, 4, 4)."""
        pose = self.root_link.pose.inv() * self.ee_link.pose
        return _pose_matrix(pose.p, pose.q)

    # --------------------------------------------------------------- control
    def reset(self):
        """Joint and pose targets of the envs being reset only (ManiSkill's mask is all-true by now)."""
        with true_reset_mask(self.scene) as mask:
            super().reset()
            self.ik_unreachable[mask] = False
            pose = self.ee_pose_at_base()
            if self._target_pose is None:
                self._target_pose = pose
            else:
                self._target_pose[mask] = pose[mask]

    def set_action(self, action: Array):
        action = self._preprocess_action(action)
        self._step = 0
        self._start_qpos = self.qpos
        # relative mode: FK of the measured joints is the measured TCP pose (same kinematics as PhysX)
        q0 = self._target_qpos if self.config.use_target else self._start_qpos
        q, ok, target = self.ik.tool_step(q0, action, self._target_pose if self.config.use_target else None)
        self._target_qpos = torch.where(ok[:, None], q, self._target_qpos)
        self._target_pose = torch.where(ok[:, None, None], target, self._target_pose)
        self.ik_unreachable = ~ok
        self.set_drive_targets(self._target_qpos)

    def set_drive_targets(self, targets: torch.Tensor):
        set_drive_targets(self, targets)

    def get_state(self) -> dict:
        """With ``use_target`` the targets are the controller's memory: the pose target (p, wxyz) and the
        joint targets its IK starts from. Part of every observation's proprioception."""
        if self.config.use_target:
            pose = self._target_pose
            return {
                "target_pose": torch.cat([pose[:, :3, 3], matrix_to_quaternion(pose[:, :3, :3])], 1),
                "target_qpos": self._target_qpos.clone(),
            }
        return {}

    def set_state(self, state: dict):
        if self.config.use_target:
            tp = state["target_pose"]
            self._target_pose = _pose_matrix(tp[:, :3], tp[:, 3:])
            self._target_qpos = state["target_qpos"].clone()


@dataclass(kw_only=True)
class PDEEDeltaToolControllerConfig(PDJointPosControllerConfig):
    """Drive gains and the URDF have no defaults: the agent owns them."""

    lower: None = None
    upper: None = None
    stiffness: Union[float, Sequence[float]]
    damping: Union[float, Sequence[float]]
    urdf_path: str
    ee_link: str = "tcp"
    pos_limit: float = TOOL_POS_LIMIT
    """metres per action along each tool axis"""
    rot_limit: float = TOOL_ROT_LIMIT
    """radians per action about the approach axis"""
    use_target: bool = False
    ik_solver: str = "auto"
    """"closed_form" (spherical wrist, exact), "dls" (any chain, iterative) or "auto" (closed form if it applies)"""
    ik_iterations: int = 6
    ik_damping: float = 1e-3
    ik_pos_tol: float = 2e-4
    ik_rot_tol: float = math.radians(0.2)
    controller_cls = PDEEDeltaToolController


class BinaryGripperController(PartialResetControllerMixin, PDJointPosController):
    """One continuous value drives both fingers: > 0 opens fully, <= 0 closes (the original report's ``open`` flag).

    Closing targets ``closed_target`` (slightly past the closed limit) so the fingers keep squeezing
    a held object with up to ``force_limit`` newtons each.
    """

    config: BinaryGripperControllerConfig

    def _initialize_action_space(self):
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def set_action(self, action: Array):
        action = self._preprocess_action(action)
        self._step = 0
        self._start_qpos = self.qpos
        if getattr(self, "_levels", None) is None:
            n = len(self.joints)
            self._levels = (
                torch.full((1, n), self.config.open_target, device=self.device),
                torch.full((1, n), self.config.closed_target, device=self.device),
            )
        self._target_qpos = torch.where(gripper_opens(action[:, :1]), *self._levels)
        self.set_drive_targets(self._target_qpos)

    def set_drive_targets(self, targets: torch.Tensor):
        set_drive_targets(self, targets)

    @property
    def commanded_open(self) -> torch.Tensor:
        """(N,) the last command opened the gripper: its finger targets stand above mid-way between the levels."""
        return self._target_qpos[:, 0] > (self.config.open_target + self.config.closed_target) / 2


@dataclass(kw_only=True)
class BinaryGripperControllerConfig(PDJointPosControllerConfig):
    """Gains, force limit and finger targets have no defaults: the agent owns them."""

    lower: None = None
    upper: None = None
    stiffness: Union[float, Sequence[float]]
    damping: Union[float, Sequence[float]]
    force_limit: Union[float, Sequence[float]]
    open_target: float
    closed_target: float
    normalize_action: bool = False
    controller_cls = BinaryGripperController


def partial_reset_pd_joint_pos_controller(config, *args, **kwargs) -> PDJointPosController:
    """ManiSkill's joint position controller, resetting only the envs being reset (what
    :class:`PartialResetControllerMixin` does), bound to the instance rather than subclassed: ManiSkill's
    replay tool converts ``pd_joint_pos`` demos to ``pd_joint_delta_pos`` only for a controller whose type is
    exactly ``PDJointPosController`` (``qpos_to_pd_joint_delta_pos`` asserts it)."""
    ctrl = PDJointPosController(config, *args, **kwargs)
    full_reset = ctrl.reset

    def reset() -> None:
        with true_reset_mask(ctrl.scene):
            full_reset()

    ctrl.reset = reset
    return ctrl


@dataclass
class PartialResetPDJointPosControllerConfig(PDJointPosControllerConfig):
    controller_cls = staticmethod(partial_reset_pd_joint_pos_controller)


class PartialResetPDEEPoseController(PartialResetControllerMixin, PDEEPoseController):
    """ManiSkill's EE pose controller, resetting only the envs being reset."""


@dataclass
class PartialResetPDEEPoseControllerConfig(PDEEPoseControllerConfig):
    controller_cls = PartialResetPDEEPoseController
