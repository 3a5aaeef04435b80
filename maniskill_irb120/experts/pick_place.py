"""Scripted experts for the IRB 120 table tasks: one pick-and-place phase machine, one subclass per task.

They read the task's public interface (``target_object``, the tray centres, the task's public actors; envs/base.py)
but act only through ``pd_ee_delta_tool`` actions
in [-1, 1]: a world-frame displacement is rotated into the TCP frame (Rᵀ·d), scaled by the ±1 cm limit, and
shrunk uniformly so its largest component is 1 (straight-line moves, no axis-wise clipping that would bend
the path into a tray wall). Yaw uses the ±10° rotation about the approach axis.

Phases (per env, batched): approach a hover point above the object while aligning the finger axis with a
side face normal (smallest rotation modulo 90°) → descend → close → lift → then per task: hold still
(GraspLift), or carry above the place → lower → open → retreat (TableClearing: the destination tray;
StackCube: the other object). ``maniskill-irb120 expert --env-id ID --episodes 100 --seed 0`` prints one
JSON line with the success rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from mani_skill.utils.structs.actor import Actor

from maniskill_irb120.action import TOOL_POS_LIMIT, TOOL_ROT_LIMIT, action_from_world_motion, tcp_rotation
from maniskill_irb120.envs import grasp_lift, stack_cube, table_clearing
from maniskill_irb120.envs.base import IRB120TableEnv, grasp_yaw_error
from maniskill_irb120.envs.scene import TRAY_INNER, TRAY_WALL_H

# gripper_base collision box half extents across the approach axis: along the fingers / across them
GRIPPER_HALF_LONG, GRIPPER_HALF_SHORT = 0.032, 0.015

APPROACH, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT, HOLD = range(9)
PHASE_NAMES = ["approach", "descend", "close", "lift", "carry", "lower", "release", "retreat", "hold"]


@dataclass
class ExpertConfig:
    hover: float = 0.06
    """TCP height above the object centre before descending (clears the 3 cm tray walls)"""
    grasp_offset: float = 0.005
    """TCP height above the object centre at the grasp: finger tips 4 mm below the centre, and the
    gripper body (17 mm above the TCP) 2 mm above the 3 cm tray walls for a 20 mm cube"""
    carry_height: float = 0.12
    """TCP height above the source tray floor while lifting and carrying"""
    release_height: float = 0.006
    """object-centre height above its resting place when the gripper opens"""
    close_steps: int = 4
    release_steps: int = 3
    pos_tol: float = 0.002
    yaw_tol: float = math.radians(2.0)
    align_tol: float = 0.004
    """reactive: TCP-to-object horizontal distance within which the gripper descends (or keeps closing)"""
    carry_tol: float = 0.005
    """reactive: a held object this far below the carry height is lifted again before it is carried"""
    funnel_xy: tuple[float, float] = (0.002, 0.012)
    """reactive: horizontal TCP-to-object distance at which the descent target starts to rise above the grasp
    height, and at which it reaches the hover height (a continuous funnel, so a learner can regress it)"""
    funnel_yaw: tuple[float, float] = (math.radians(2.0), math.radians(12.0))
    """reactive: the same funnel for the yaw error"""
    grasp_tol: float = 0.003
    """reactive: TCP height slack around the grasp height within which an aligned open gripper closes"""


class PickPlaceExpert:
    """Batched phase machine; call :meth:`reset` after ``env.reset`` and :meth:`act` each step.

    It picks the task's ``target_object``; a task's expert says where to put it (:meth:`_place`: the object
    centre's resting point there, or None to hold it at the carry height instead) and registers itself with
    :func:`register_expert`."""

    default_config = ExpertConfig()

    def __init__(self, env: IRB120TableEnv, config: ExpertConfig | None = None, reactive: bool = False):
        self.env = env
        self.cfg = config or self.default_config
        self.reactive = reactive
        n, dev = env.num_envs, env.device
        self.phase = torch.zeros(n, dtype=torch.long, device=dev)
        self.counter = torch.zeros(n, dtype=torch.long, device=dev)
        self.grasp_xy = torch.zeros(n, 2, device=dev)
        self.funnel = torch.zeros(n, device=dev)  # reactive: 0 = descend to the grasp, 1 = hover

    def reset(self, env_idx: torch.Tensor | None = None):
        idx = slice(None) if env_idx is None else env_idx
        self.phase[idx] = APPROACH
        self.counter[idx] = 0

    def _object(self) -> Actor:
        return self.env.target_object

    def _place(self) -> torch.Tensor | None:
        return None

    def _yaw_error(self, tcp_rot: torch.Tensor) -> torch.Tensor:
        """Rotation about the TCP approach axis that aligns the finger axis with a cube face normal.

        The cube allows two finger directions (90° apart). The gripper body is 64 mm long along the
        finger axis but 30 mm across, so near a tray wall the direction that keeps the long side
        parallel to the wall wins; otherwise the smaller rotation does.
        """
        env = self.env
        obj = self._object()
        fingers = tcp_rot[:, :, 1]
        finger_ang = torch.atan2(fingers[:, 1], fingers[:, 0])
        e1 = grasp_yaw_error(obj.pose.raw_pose, env.agent.tcp_pose.raw_pose)
        e2 = e1 - torch.where(e1 >= 0, 1.0, -1.0) * (math.pi / 2)
        rel = (obj.pose.p[:, :2] - env.source_center[:, :2]).abs()
        wall_gap = TRAY_INNER / 2 - rel  # (N, 2) distance from the object centre to the nearest x / y wall

        def margin(e: torch.Tensor) -> torch.Tensor:
            ux, uy = torch.cos(finger_ang + e).abs(), torch.sin(finger_ang + e).abs()
            ext_x = GRIPPER_HALF_LONG * ux + GRIPPER_HALF_SHORT * uy
            ext_y = GRIPPER_HALF_LONG * uy + GRIPPER_HALF_SHORT * ux
            return torch.minimum(wall_gap[:, 0] - ext_x, wall_gap[:, 1] - ext_y)

        world_err = torch.where(margin(e2) > margin(e1) + 0.003, e2, e1)
        # a rotation by a about TCP x is a rotation by a * (x · ẑ) about world z
        return world_err * torch.sign(tcp_rot[:, 2, 0])

    def _targets(self, phase: torch.Tensor, tcp_p: torch.Tensor, place: torch.Tensor | None):
        """World-frame TCP target and gripper command (+1 open) for each env's phase."""
        env, c = self.env, self.cfg
        obj_p = self._object().pose.p
        h = env.object_half_size
        floor = env.source_center[:, 2]
        target = tcp_p.clone()
        gripper = -torch.ones(env.num_envs, device=env.device)

        m = phase == APPROACH
        target[m, :2] = obj_p[m, :2]
        target[m, 2] = floor[m] + h + c.hover
        m = phase == DESCEND
        target[m, :2] = obj_p[m, :2]
        target[m, 2] = floor[m] + h + c.grasp_offset
        if self.reactive:  # one funnel from the hover point down to the grasp, its height set by the misalignment
            m = (phase == APPROACH) | (phase == DESCEND)
            target[m, 2] = floor[m] + h + c.grasp_offset + (c.hover - c.grasp_offset) * self.funnel[m]
        m = (phase == LIFT) | (phase == HOLD)
        target[m, :2] = self.grasp_xy[m]
        target[m, 2] = floor[m] + c.carry_height
        if place is not None:
            m = phase == CARRY
            target[m, :2] = place[m, :2]
            target[m, 2] = floor[m] + c.carry_height
            m = phase == LOWER  # the TCP is grasp_offset above the held object's centre
            target[m, :2] = place[m, :2]
            target[m, 2] = place[m, 2] + c.release_height + c.grasp_offset
            m = phase == RETREAT
            target[m, 2] = place[m, 2] + TRAY_WALL_H + 0.06
        gripper[(phase <= DESCEND) | ((phase >= RELEASE) & (phase != HOLD))] = 1.0
        return target, gripper

    def act(self) -> torch.Tensor:
        """(N, 5) action for the current state; advances each env's phase first."""
        c = self.cfg
        tcp = self.env.agent.tcp_pose
        tcp_p = tcp.p
        tcp_rot = tcp_rotation(tcp.raw_pose)
        yaw_err = self._yaw_error(tcp_rot)
        place = self._place()
        if self.reactive:
            self.phase = self._infer_phase(tcp_p, yaw_err, place)
        ph = self.phase

        target, _ = self._targets(ph, tcp_p, place)
        dist = torch.linalg.norm(target - tcp_p, dim=1)
        reached = dist < c.pos_tol
        aligned = yaw_err.abs() < c.yaw_tol
        nxt = ph.clone()
        if not self.reactive:  # a reactive expert's pick phases and its CLOSE and RELEASE come from the state
            nxt[(ph == APPROACH) & reached & aligned] = DESCEND
            nxt[(ph == DESCEND) & reached & aligned] = CLOSE
            nxt[(ph == CLOSE) & (self.counter >= c.close_steps)] = LIFT
            nxt[(ph == RELEASE) & (self.counter >= c.release_steps)] = RETREAT
        nxt[(ph == LIFT) & (dist < 0.005)] = CARRY if place is not None else HOLD
        nxt[(ph == CARRY) & (dist < 0.003)] = LOWER
        nxt[(ph == LOWER) & reached] = RELEASE
        entered = nxt != ph
        self.counter[entered] = 0
        self.grasp_xy[entered & (nxt == LIFT)] = tcp_p[entered & (nxt == LIFT), :2]
        self.counter[(nxt == CLOSE) | (nxt == RELEASE)] += 1
        self.phase = nxt

        target, gripper = self._targets(nxt, tcp_p, place)
        yaw = torch.where((nxt == APPROACH) | (nxt == DESCEND), yaw_err, torch.zeros_like(yaw_err))
        # the tool action's own scale; the default one when the env this expert reads runs another control mode
        # (a digital twin driven in joint targets: its actions go to a robot in pd_ee_delta_tool's units)
        cfg = self.env.agent.arm_controller.config
        pos_limit, rot_limit = getattr(cfg, "pos_limit", TOOL_POS_LIMIT), getattr(cfg, "rot_limit", TOOL_ROT_LIMIT)
        return action_from_world_motion(target - tcp_p, yaw, gripper, tcp_rot, pos_limit, rot_limit)

    def _infer_phase(self, tcp_p: torch.Tensor, yaw_err: torch.Tensor, place: torch.Tensor | None) -> torch.Tensor:
        """Each env's phase read from the state alone (no step counter, no memory), so the expert can label
        any state a learner visits (DAgger). The transitions in :meth:`act` then run from it as usual."""
        env, c = self.env, self.cfg
        obj = self._object()
        obj_p = obj.pose.p
        holding = env.agent.is_grasping(obj)
        opening = env.agent.gripper_opening
        width = 2 * torch.as_tensor(env.object_half_size, device=env.device)
        floor = env.source_center[:, 2]
        carry_z = floor + c.carry_height
        xy_obj = torch.linalg.norm(tcp_p[:, :2] - obj_p[:, :2], dim=1)
        grasp_z = floor + env.object_half_size + c.grasp_offset

        def ramp(x: torch.Tensor, lo_hi: tuple[float, float]) -> torch.Tensor:
            return ((x - lo_hi[0]) / (lo_hi[1] - lo_hi[0])).clamp(0, 1)

        self.funnel = torch.maximum(ramp(xy_obj, c.funnel_xy), ramp(yaw_err.abs(), c.funnel_yaw))
        phase = torch.full_like(self.phase, APPROACH)
        phase[self.funnel < 1] = DESCEND
        aligned = (xy_obj < c.align_tol) & (yaw_err.abs() < 2 * c.yaw_tol)
        at_grasp = aligned & (tcp_p[:, 2] - grasp_z < c.grasp_tol)
        phase[at_grasp & (opening > 0.5 * width)] = CLOSE  # open or closing, not yet squeezing
        low = tcp_p[:, 2] < carry_z - c.carry_tol
        if place is None:
            phase[holding] = LIFT
        else:
            xy_place = torch.linalg.norm(obj_p[:, :2] - place[:, :2], dim=1)
            placed = ~holding & (torch.linalg.norm(obj_p - place, dim=1) < 0.02)
            phase[placed] = RETREAT
            lowering = holding & ((xy_place < 0.003) | ((xy_place < 0.01) & low))
            phase[holding & ~lowering] = CARRY
            phase[holding & ~lowering & low] = LIFT
            phase[lowering] = LOWER
        self.grasp_xy[phase == LIFT] = tcp_p[phase == LIFT, :2]
        return phase


EXPERTS: dict[str, type[PickPlaceExpert]] = {}
"""env id -> expert class; :func:`register_expert` fills it"""


def register_expert(env_id: str):
    """Class decorator: the scripted expert of task ``env_id`` (a new task's expert is one small subclass)."""

    def deco(cls: type[PickPlaceExpert]) -> type[PickPlaceExpert]:
        EXPERTS[env_id] = cls
        return cls

    return deco


@register_expert(table_clearing.ENV_ID)
class TableClearingExpert(PickPlaceExpert):
    """Into the destination tray, released ``release_height`` above its floor."""

    def _place(self) -> torch.Tensor:
        place = self.env.dest_center.clone()
        place[:, 2] += self.env.object_half_size
        return place


@register_expert(grasp_lift.ENV_ID)
class GraspLiftExpert(PickPlaceExpert):
    """Lift the object's centre 12.5 cm above the tray floor (the task asks 10 cm) and hold it there."""

    default_config = replace(ExpertConfig(), carry_height=0.13)


@register_expert(stack_cube.ENV_ID)
class StackCubeExpert(PickPlaceExpert):
    """cube_a onto cube_b: carried 8 cm above the floor (clears cube_b), released 3 mm above its top."""

    default_config = replace(ExpertConfig(), carry_height=0.08, release_height=0.003)

    def _place(self) -> torch.Tensor:
        return stack_cube.place_on(self.env.cube_b.pose.raw_pose, self.env.object_half_size)


def expert_for(env, reactive: bool = False) -> PickPlaceExpert:
    """The scripted expert of ``env``'s task (a gym env or its unwrapped ManiSkill env); ``reactive``: its
    phase is read from the state every step (see :meth:`PickPlaceExpert._infer_phase`)."""
    u = env.unwrapped
    env_id = u.spec.id if u.spec is not None else None
    if env_id not in EXPERTS:
        raise ValueError(f"no scripted expert for env {env_id!r}; experts exist for {sorted(EXPERTS)}")
    return EXPERTS[env_id](u, reactive=reactive)
