"""GraspLift-IRB120-v1: grasp the object in the source tray and hold it at least 10 cm above the tray
floor, still, for one second. The first skill of the original report's table clearing, on its own."""

from __future__ import annotations

from typing import Any

import torch
from mani_skill.utils.registration import register_env

from maniskill_irb120.envs.base import IRB120TableEnv, grasp_approach_reward, step_grasp_yaw_error
from maniskill_irb120.maniskill_compat import raw_pose

ENV_ID = "GraspLift-IRB120-v1"
LIFT_HEIGHT = 0.10  # object centre above the source tray floor
HOLD_STEPS = 20  # one second at the 20 Hz control rate
STILL_SPEED = 0.02  # m/s: "still" means the object moves slower than this
SETTLE_SPEED = 0.05  # m/s: the settle term 1 - tanh(speed / SETTLE_SPEED) is 0.62 at "still", ~0 at full speed


@register_env(ENV_ID, max_episode_steps=150)
class GraspLiftIRB120Env(IRB120TableEnv):
    """Grasp the object and hold it >= 10 cm above the source tray floor, still, for 1 s.

    **Randomisation:** as TableClearing: object uniform in the source tray (shrunk by ``spawn_margin``),
    uniform yaw; robot at ``rest`` plus optional joint noise.

    **Events** (``(N,)`` in ``info``): ``grasped`` (the gripper commanded closed, both fingers squeeze it and it
    touches nothing of the scene: envs/base.py ``_grasped``), ``lifted`` (centre >= 10 cm above the tray floor),
    ``object_speed`` (m/s over the last control step), ``still`` (speed < 2 cm/s on a step whose command the
    controller applied: an arm frozen because the IK refused its target is stuck, not holding), ``hold_steps``
    (consecutive control steps grasped, lifted and still), ``success`` (``hold_steps`` reached 20), ``fail`` =
    ``collided`` (a robot link but the base pushes on the table, a tray or the floor).

    **Rewards:** ``dense`` is staged in [0, 4], ``normalized_dense`` (default) = dense / 4, ``sparse`` = success.
    Each stage's band lies above the last (``floor(dense)`` is the stage; envs/base.py ``MAX_STAGED_REWARD``):

    =====  ===========================  =============================================  ========
    stage  state                        dense                                          range
    =====  ===========================  =============================================  ========
    0      not grasped                  grasp approach (envs/base.py)                  [0, 1)
    1      grasped, below 10 cm         1 + height / 10 cm                             [1, 2)
    2      grasped and lifted           2 + (settle + hold_steps / 20) / 2             [2, 3)
    4      success                      4                                              4
    -      collision                    0                                              0
    =====  ===========================  =============================================  ========

    ``settle`` = ``1 - tanh(speed / 5 cm/s)``, 0 for a step whose command the controller refused
    (``ik_unreachable``), and ``still`` excludes refused steps: the hold pays for slowing the object down, and a
    frozen arm is stuck, not holding (why: docs/reward_design.md, "GraspLift's hold stage").

    **Episode length:** 150 steps (the scripted expert needs 60).
    """

    def _load_scene(self, options: dict):
        self.build_trays()
        self.obj = self.target_object = self._build_object("object", [0.8, 0.1, 0.1, 1])
        self.build_background()
        self.watch_contacts([self.obj])

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        u = self._episode_draws(env_idx, joint_noise=6, obj_xy=2, obj_yaw=1)
        self._reset_robot(env_idx, u["joint_noise"])
        self.obj.set_pose(self._spawn_in_source_tray(u["obj_xy"], u["obj_yaw"]))

    def privileged_state(self) -> dict[str, torch.Tensor]:
        return dict(obj_pose=raw_pose(self.obj))

    def evaluate(self) -> dict:
        state = self._read_step_state()
        obj_p = state["obj_pose"][:, :3]
        speed = self._speed("obj_p", obj_p)
        contacts = self.contacts.flags()
        height = obj_p[:, 2] - self.source_center[:, 2]
        grasped = self._grasped(contacts.finger_forces[0], state["tcp_pose"][:, 3:]) & ~contacts.object_hit[0]
        lifted = height >= LIFT_HEIGHT
        common = self._common_info(contacts.robot_hit, grasped)
        still = (speed < STILL_SPEED) & ~common["ik_unreachable"]
        held_before = self._last("hold_steps", torch.zeros_like(grasped, dtype=torch.long))
        hold_steps = torch.where(grasped & lifted & still, held_before + 1, 0)
        self._previous(dict(hold_steps=hold_steps, obj_p=obj_p))
        return dict(
            **common,
            success=hold_steps >= HOLD_STEPS,
            lifted=lifted,
            still=still,
            hold_steps=hold_steps,
            object_height=height,
            object_speed=speed,
        )

    def state_observations(self, state: dict[str, torch.Tensor], info: dict) -> dict[str, torch.Tensor]:
        """Without the count of still steps: it changes no right action (keep still until it reaches 20), and
        sampled actions are seldom still for more than a few steps, so a policy trained by RL only ever
        extrapolated from it. PPO's mean action held the object nearly still and jerked as the count reached 3,
        every time; with the count zeroed, the same policy succeeded (docs/notes/rl-from-the-reward.md)."""
        obj, tcp = state["obj_pose"], state["tcp_pose"]
        return dict(
            obj_pose=obj.clone(),
            source_tray_pos=self.source_center.clone(),
            tcp_to_obj_pos=obj[:, :3] - tcp[:, :3],
            tcp_to_obj_yaw=step_grasp_yaw_error(state, "obj_pose")[:, None],
        )

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """Staged, stage k paying k + progress in [0, 1) (the table in the class docstring)."""
        reach = grasp_approach_reward(
            self.step_state["obj_pose"], self.tcp_pose, step_grasp_yaw_error(self.step_state, "obj_pose")
        )
        lift = (info["object_height"] / LIFT_HEIGHT).clamp(0, 1)
        hold = (info["hold_steps"].float() / HOLD_STEPS).clamp(max=1)
        settle = torch.where(info["ik_unreachable"], 0.0, 1 - torch.tanh(info["object_speed"] / SETTLE_SPEED))
        reward = torch.where(info["lifted"], 2 + (settle + hold) / 2, 1 + lift)
        reward = torch.where(info["grasped"], reward, reach)
        reward = torch.where(info["success"], self.MAX_STAGED_REWARD, reward)
        return torch.where(info["fail"], 0.0, reward)
