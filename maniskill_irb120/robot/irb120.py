"""The ABB IRB 120 with a MetalWork W155032001 gripper and a hand-mounted RGB-D camera."""

from __future__ import annotations

import math
from copy import deepcopy

import numpy as np
import sapien
import torch
from mani_skill.agents.base_agent import BaseAgent, Keyframe
from mani_skill.agents.controllers import PDJointPosController, deepcopy_dict
from mani_skill.agents.registration import register_agent
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import common
from mani_skill.utils.structs.actor import Actor

from maniskill_irb120.robot.controllers import (
    BinaryGripperController,
    BinaryGripperControllerConfig,
    PartialResetPDEEPoseControllerConfig,
    PartialResetPDJointPosControllerConfig,
    PDEEDeltaToolControllerConfig,
)
from maniskill_irb120.robot.description import geometry, urdf_path
from maniskill_irb120.robot.shaders import FORWARD, sensor_shader_config

ARM_JOINTS = [f"joint_{i}" for i in range(1, 7)]
FINGER_STROKE = geometry()["finger_stroke"]  # each finger's travel from closed (2 mm gap) to open (26 mm)
GRIPPER_JOINTS = ["finger_left_joint", "finger_right_joint"]

# Hand camera per the original report: eye 3 cm behind and 2 cm above the TCP, looking along the approach axis.
# SAPIEN cameras look along their local +x with +z up, which is exactly the TCP frame's convention.
# Shaded by our one-pass pack (same images as ManiSkill's "minimal", cheaper on a CPU; see shaders.py).
HAND_CAMERA = dict(offset=(-0.03, 0.0, 0.02), width=84, height=84, fov=math.pi / 2, near=0.001, far=2.0, shader=FORWARD)


def hand_camera_shader(name: str, render_device: sapien.Device) -> str:
    """Our one-pass pack helps the CPU rasteriser only; a GPU renders ManiSkill's ``minimal`` (same
    images, proven under its batched camera groups) instead."""
    return "minimal" if name == FORWARD and render_device.is_cuda() else name


@register_agent()
class IRB120Metalwork(BaseAgent):
    """ABB IRB 120 + MetalWork W155032001. TCP frame: +x approach, +y finger opening (left), +z camera side.

    Control modes: ``pd_ee_delta_tool`` (the original report's action: δx, δy, δz in the TCP frame, ±1 cm;
    rotation about the approach axis, ±10°; gripper), ``pd_ee_target_delta_tool`` (same, relative to the
    last target instead of the measured pose), ``pd_joint_pos``, ``pd_joint_delta_pos`` and
    ``pd_ee_delta_pose`` (ManiSkill's own). The gripper is one value in every mode: > 0 open, <= 0 close.
    """

    uid = "irb120_metalwork"
    urdf_config = dict(
        _materials=dict(pad=dict(static_friction=2.0, dynamic_friction=2.0, restitution=0.0)),
        link=dict(
            finger_left=dict(material="pad", patch_radius=0.1, min_patch_radius=0.1),
            finger_right=dict(material="pad", patch_radius=0.1, min_patch_radius=0.1),
        ),
    )
    disable_self_collisions = True

    keyframes = dict(
        # TCP at (0.35, 0, 0.25) m in the base frame, approach axis pointing straight down, gripper open
        rest=Keyframe(
            qpos=np.array([0.0, 0.3325, 0.4627, 0.0, 0.7756, 0.0, FINGER_STROKE, FINGER_STROKE]),
            pose=sapien.Pose(),
        ),
        zero=Keyframe(qpos=np.zeros(8), pose=sapien.Pose()),
    )

    arm_joint_names = ARM_JOINTS
    gripper_joint_names = GRIPPER_JOINTS
    ee_link_name = "tcp"

    # Stiff, lightly damped drives: a 1 cm / 10 deg tool step is tracked to >99% within one 50 ms
    # control period (5 physics steps at 100 Hz), which the original report got by waiting for convergence.
    arm_stiffness = 1e5
    arm_damping = 500.0
    arm_force_limit = 800.0

    gripper_stiffness = 1e3  # ~10 N squeeze on a 20 mm cube; stiffer drives chatter on the 20 g fingers
    gripper_damping = 100.0
    gripper_force_limit = 40.0
    gripper_squeeze = 0.002  # m past the closed stop: the drive keeps pushing on a held object

    def __init__(self, *args, hand_camera: dict | None = None, **kwargs):
        self.hand_camera_cfg = {**HAND_CAMERA, **(hand_camera or {})}
        super().__init__(*args, **kwargs)

    @property
    def urdf_path(self) -> str:  # built from the xacro sources on first use, then cached
        return urdf_path()

    @property
    def _sensor_configs(self):
        c = self.hand_camera_cfg
        return [
            CameraConfig(
                uid="hand_camera",
                pose=sapien.Pose(p=list(c["offset"])),
                width=c["width"],
                height=c["height"],
                fov=c["fov"],
                near=c["near"],
                far=c["far"],
                mount=self.robot.links_map[self.ee_link_name],
                shader_config=sensor_shader_config(hand_camera_shader(c["shader"], self.scene.backend.render_device)),
            )
        ]

    @property
    def _controller_configs(self):
        arm_kw = dict(stiffness=self.arm_stiffness, damping=self.arm_damping, force_limit=self.arm_force_limit)
        gripper = BinaryGripperControllerConfig(
            self.gripper_joint_names,
            stiffness=self.gripper_stiffness,
            damping=self.gripper_damping,
            force_limit=self.gripper_force_limit,
            open_target=FINGER_STROKE,
            closed_target=-self.gripper_squeeze,
        )
        tool = PDEEDeltaToolControllerConfig(
            self.arm_joint_names, ee_link=self.ee_link_name, urdf_path=self.urdf_path, **arm_kw
        )
        tool_target = deepcopy(tool)
        tool_target.use_target = True
        joint_pos = PartialResetPDJointPosControllerConfig(
            self.arm_joint_names, lower=None, upper=None, normalize_action=False, **arm_kw
        )
        joint_delta = PartialResetPDJointPosControllerConfig(
            self.arm_joint_names, lower=-0.1, upper=0.1, use_delta=True, **arm_kw
        )
        ee_delta_pose = PartialResetPDEEPoseControllerConfig(
            self.arm_joint_names,
            pos_lower=-0.1,
            pos_upper=0.1,
            rot_lower=-0.1,
            rot_upper=0.1,
            ee_link=self.ee_link_name,
            urdf_path=self.urdf_path,
            **arm_kw,
        )
        return deepcopy_dict(
            dict(
                pd_ee_delta_tool=dict(arm=tool, gripper=gripper),
                pd_ee_target_delta_tool=dict(arm=tool_target, gripper=gripper),
                pd_joint_pos=dict(arm=joint_pos, gripper=gripper),
                pd_joint_delta_pos=dict(arm=joint_delta, gripper=gripper),
                pd_ee_delta_pose=dict(arm=ee_delta_pose, gripper=gripper),
            )
        )

    def _after_init(self):
        links = self.robot.links_map
        self.finger_left = links["finger_left"]
        self.finger_right = links["finger_right"]
        self.tcp = links[self.ee_link_name]
        self.invalid_action = torch.zeros(self.scene.num_envs, dtype=torch.bool, device=self.device)
        self._step_start_qpos: torch.Tensor | None = None  # qpos when the last action was set (step_qvel)
        # maps a quaternion's outer product (w, x, y, z) to its rotation matrix's second column (is_grasping)
        m = torch.zeros(4, 4, 3)
        m[1, 2, 0], m[0, 3, 0] = 2.0, -2.0  # 2xy - 2wz
        m[0, 0, 1], m[2, 2, 1], m[1, 1, 1], m[3, 3, 1] = 1.0, 1.0, -1.0, -1.0  # w² + y² - x² - z²
        m[2, 3, 2], m[0, 1, 2] = 2.0, 2.0  # 2yz + 2wx
        self._opening_map = m.reshape(16, 3).to(self.device)
        self._closing_sign = torch.tensor([[1.0], [-1.0]], device=self.device)  # left +, right - (is_grasping)

    # ------------------------------------------------------------------ actions
    def set_action(self, action):
        """Validate before anything reaches a controller. Shape: always. Finiteness: on the CPU a
        ``ValueError``; on CUDA a check would wait for the GPU every step, so non-finite rows are replaced
        by the hold action on the device and flagged in ``invalid_action`` (``info["invalid_action"]``)."""
        if self.control_mode is None:
            raise ValueError("no control mode set on the agent")
        expected = (self.scene.num_envs, self.action_space.shape[-1])
        action = common.to_tensor(action, device=self.device)
        if tuple(action.shape) != expected:
            raise ValueError(
                f"action has shape {tuple(action.shape)}, expected {expected} for control mode {self.control_mode!r}"
            )
        if action.device.type == "cpu":
            # numpy where it can read the dtype: a third of torch's cost on one row
            numpy_ok = action.dtype in (torch.float32, torch.float64)
            if not (np.isfinite(action.detach().numpy()).all() if numpy_ok else bool(torch.isfinite(action).all())):
                raise ValueError(f"action contains NaN or inf: {action.detach().float().numpy()}")
            self.invalid_action = torch.zeros(expected[0], dtype=torch.bool)
        else:
            action, self.invalid_action = self.hold_nonfinite(action)
        self._step_start_qpos = self.robot.get_qpos().clone()  # for step_qvel
        self.controller.set_action(action)

    def hold_nonfinite(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(action with each non-finite row replaced by the hold action, (N,) bool of those rows); no sync."""
        bad = ~torch.isfinite(action).all(dim=1)
        return torch.where(bad[:, None], self.hold_action(), action), bad

    def hold_action(self) -> torch.Tensor:
        """(N, A) action that keeps every joint target where it is: zero for delta arm modes, the current
        joint targets for absolute ones (unnormalised in our configs), the gripper's current command."""
        parts = []
        for ctrl in self.controller.controllers.values():
            n, dim = ctrl._target_qpos.shape[0], ctrl.action_space.shape[-1]
            if isinstance(ctrl, BinaryGripperController):
                parts.append(torch.where(ctrl.commanded_open[:, None], 1.0, -1.0))
            elif (
                isinstance(ctrl, PDJointPosController)
                and not ctrl.config.use_delta
                and not ctrl.config.normalize_action
            ):
                parts.append(ctrl._target_qpos.clone())
            else:
                parts.append(torch.zeros(n, dim, device=self.device))
        return torch.cat(parts, dim=1)

    @property
    def arm_controller(self):
        return self.controller.controllers["arm"]

    @property
    def ik_unreachable(self) -> torch.Tensor:
        """(N,) bool: the last tool-frame target could not be reached and was not applied."""
        ctrl = self.arm_controller
        if hasattr(ctrl, "ik_unreachable"):
            return ctrl.ik_unreachable
        return torch.zeros(self.scene.num_envs, dtype=torch.bool, device=self.device)

    # ------------------------------------------------------------------ state
    @property
    def tcp_pos(self):
        return self.tcp.pose.p

    @property
    def tcp_pose(self):
        return self.tcp.pose

    @property
    def gripper_opening(self) -> torch.Tensor:
        """(N,) distance between the finger pads in metres."""
        q = self.robot.get_qpos()[:, -2:]
        return q.sum(dim=1) + 2 * geometry()["finger_closed_half_gap"]

    @property
    def gripper_commanded_closed(self) -> torch.Tensor:
        """(N,) the gripper's last command was "close" (its drive target below mid-stroke): a pneumatic gripper
        holds only when closed, and it is all the real side knows of a grasp (``sim2real/env.py``)."""
        return ~self.controller.controllers["gripper"].commanded_open

    def is_grasping(
        self,
        object: Actor,
        min_force: float = 0.5,
        max_angle: float = 85.0,
        finger_forces: tuple[torch.Tensor, torch.Tensor] | torch.Tensor | None = None,
        tcp_quat: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Both fingers push on ``object`` with at least ``min_force`` N roughly along their closing direction.

        ``finger_forces``: the (N,3) contact forces on the left and right finger from ``object`` (or both as one
        (2, N, 3) tensor), and
        ``tcp_quat`` the (N,4) wxyz TCP orientation, when the caller already has them (a task that scans
        the contact list and reads poses once per step); else queried here.
        """
        if finger_forces is None:
            finger_forces = (
                self.scene.get_pairwise_contact_forces(self.finger_left, object),
                self.scene.get_pairwise_contact_forces(self.finger_right, object),
            )
        if isinstance(finger_forces, torch.Tensor):  # (2, N, 3), as a contact scan gives them: two ops, not four
            push = finger_forces.transpose(0, 1) * self._closing_sign
        else:
            lf, rf = finger_forces
            push = torch.stack([lf, -rf], 1)  # (N, 2, 3): each finger's force, signed towards its closing direction
        # both fingers slide along the TCP's y axis (left opens towards +y, right towards -y): the rotation
        # matrix's second column, [2(xy - wz), 1 - 2(x² + z²), 2(yz + wx)], as one product of the
        # quaternion's outer product with a constant (this runs every step; fewer small ops is faster)
        q = self.tcp.pose.q if tcp_quat is None else tcp_quat
        opening = (q[:, :, None] * q[:, None, :]).reshape(-1, 16) @ self._opening_map  # unit q: w²+x²+y²+z² = 1
        norm = torch.linalg.vector_norm(push, dim=2)
        along = (push @ opening[:, :, None])[..., 0]
        return ((norm >= min_force) & (along >= math.cos(math.radians(max_angle)) * norm)).all(1)

    def is_static(self, threshold: float = 0.2) -> torch.Tensor:
        qvel = self.robot.get_qvel()[..., :6]
        return torch.max(torch.abs(qvel), dim=1)[0] <= threshold

    def set_step_start(self, env_idx: torch.Tensor, qpos: torch.Tensor) -> None:
        """The last step of envs ``env_idx`` started at ``qpos`` (their ``step_qvel`` measures from it): their
        reset pose after a reset (``qvel`` zero), or the one a restored env state carries."""
        if self._step_start_qpos is None:
            self._step_start_qpos = self.robot.get_qpos().clone()
        self._step_start_qpos[env_idx] = qpos.to(self._step_start_qpos)

    def get_memory(self) -> dict[str, torch.Tensor]:
        """(N, D) rows of what the observation and ``info`` read from the agent beyond the physics, for the env
        state: where the last step started (``qvel``) and the gripper's last command (a grasp needs it closed)."""
        start = self._step_start_qpos if self._step_start_qpos is not None else self.robot.get_qpos()
        gripper = self.controller.controllers["gripper"]
        return dict(step_start_qpos=start.clone(), gripper_target=gripper._target_qpos.clone())

    def set_memory(self, env_idx: torch.Tensor, memory: dict[str, torch.Tensor] | None) -> None:
        """Rows ``env_idx`` of :meth:`get_memory`. None (a state recorded without it): at rest (``qvel`` zero, as
        after a reset), and the gripper commanded as its fingers stand (closed below mid-stroke)."""
        gripper = self.controller.controllers["gripper"]
        if memory is None:
            qpos = self.robot.get_qpos()[env_idx]
            cfg = gripper.config
            closed = qpos[:, -1:] < (cfg.open_target + cfg.closed_target) / 2
            target = torch.where(closed, cfg.closed_target, cfg.open_target).expand(-1, len(gripper.joints))
            memory = dict(step_start_qpos=qpos, gripper_target=target)
        self.set_step_start(env_idx, memory["step_start_qpos"])
        targets = gripper._target_qpos.clone()
        targets[env_idx] = memory["gripper_target"].to(targets)
        gripper._target_qpos = targets

    def step_qvel(self) -> torch.Tensor:
        """(N, dof) the joints' mean velocity over the last control step: (qpos now - qpos when the step's action
        was set) x control frequency. The observation's ``qvel``, rather than PhysX's instantaneous joint velocity:
        at the end of a period the drives have all but settled, and what remains (~1e-3 rad/s) is a drive
        transient no real robot reports (an IRC5 standing at its target reads zero). Policies learned to read
        it (a state DAgger policy lost a fifth of its sim successes with it zeroed), so the twin could not match
        them; a step's displacement over the period is what both sides measure alike (``sim2real/agent.py``)."""
        qpos = self.robot.get_qpos()
        if self._step_start_qpos is None:
            return torch.zeros_like(qpos)
        return (qpos - self._step_start_qpos) * self._control_freq

    def get_proprioception(self):
        obs = super().get_proprioception()
        obs["qvel"] = self.step_qvel()
        obs["gripper_opening"] = self.gripper_opening.unsqueeze(1)
        return obs
