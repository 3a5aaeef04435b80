"""TableClearing-IRB120-v1: move an object from the yellow source tray to the green destination tray.

The scene, events and dense reward follow the original report.
Everything is batched over ``(num_envs, ...)`` torch tensors, on ``physx_cpu`` and ``physx_cuda`` alike.
"""

from __future__ import annotations

from typing import Any

import torch
from mani_skill.utils.registration import register_env

from maniskill_irb120.envs.base import IRB120TableEnv, grasp_approach_reward, reach_reward, step_grasp_yaw_error, up
from maniskill_irb120.envs.scene import DEST_TRAY_XY, TRAY_FLOOR_TOP, TRAY_INNER, TRAY_WALL_H
from maniskill_irb120.maniskill_compat import raw_pose

ENV_ID = "TableClearing-IRB120-v1"
GRASP_LIFT = 0.05  # "grasped" needs the object centre >= 5 cm above the source tray floor
APPROACH_MOVE_LIMIT = 0.05  # the approach term is active only until the object moved this far
HELD_PLACE_SHARE = 0.5  # normalized_dense: the share of stage 3's band the place term pays while still held
RELEASE_SHARE = 0.25  # normalized_dense: the further share a held object's gripper command earns as it nears "open"
R_APPROACH, R_CARRY, R_TIME = 1.0, 1.0, -1.0
R_COLLISION, R_GRASP, R_DROP, R_DELIVERY = -1000.0, 100.0, -200.0, 200.0
REWARD_TERMS = ("r_approach", "r_carry", "r_time", "r_collision", "r_grasp", "r_drop", "r_delivery")


@register_env(ENV_ID, max_episode_steps=250)
class TableClearingIRB120Env(IRB120TableEnv):
    """Pick the object in the yellow tray and release it inside the green tray.

    **Randomisation:** the object's centre is uniform in the source tray's inner square shrunk by
    ``spawn_margin`` (3 cm), its yaw uniform in [0, 2π), resting on the tray floor; the robot at the
    ``rest`` keyframe plus optional joint noise (see :class:`IRB120TableEnv` for the shared arguments).

    **Events** (all ``(N,)`` bool in ``info``):

    - ``grasped``: both fingers squeeze the object (``agent.is_grasping``), nothing but the robot
      touches it, and its centre is >= 5 cm above the source tray floor (the original report's definition).
    - ``held_closed``: held (both fingers squeeze it, nothing else touches it) with the gripper commanded closed,
      at any height: the staged reward's grasp.
    - ``collided`` (= ``fail``): a robot link other than ``base_link`` (which stands on the table)
      pushes on the table, a tray or the ground with more than 0.01 N.
    - ``dropped``: grasped at t-1, not at t, and the object's centre is not over the destination
      tray's inner square.
    - ``delivered`` (= ``success``): the object's centre is over the destination tray's inner square,
      below its wall top and touches neither finger, i.e. it was released in the tray. The original report only
      said "reached the destination tray"; requiring the release keeps a held object from counting.

    **Dense reward** (``reward_mode="dense"``: the original report's terms, each also in ``info``): approach
    ±1 while not grasped and the object is within 5 cm of its start (+1 if the TCP got closer to it); carry
    ±1 while grasped (+1 if the TCP got closer to the destination tray centre); time -1; collision -1000;
    grasp +100 on the not-grasped → grasped edge; drop -200; delivery +200 on the not-delivered → delivered
    edge.

    **Normalized dense reward** (``reward_mode="normalized_dense"``, the default): staged, (stage + progress) / 4
    with progress in [0, 1), so each stage's band lies above the last (envs/base.py ``MAX_STAGED_REWARD``):

    =====  ==========================================  ==========================================  ==========
    stage  state                                       dense (normalised = this / 4)               range
    =====  ==========================================  ==========================================  ==========
    0      not held closed                             grasp approach (envs/base.py)              [0, 1)
    1      ``held_closed``, below 5 cm                 1 + height above the floor / 5 cm           [1, 2)
    2      ``held_closed``, >= 5 cm up                 2 + 1 - tanh(3·distance to the place)       [2, 3)
    3      over the dest tray, held                    3 + (½ + ¼ release) (1 - tanh(3·distance    [3, 3.75)
                                                       to the place)
    3      over the dest tray, let go (falling or in)  3 + 1 - tanh(3·distance to the place)       [3, 4)
    4      ``delivered`` (success)                     4                                           4
    -      collision                                   0                                           0
    =====  ==========================================  ==========================================  ==========

    Held at its place the object earns at most 3.75, below letting it go (3 + place, then 4), so releasing is
    never a step down; ``release`` (the gripper command mapped to [0, 1]) pays its approach to "open" there, as
    ManiSkill's StackCube "ungrasp" term does for a binary gripper. A released object falls through stage 3, not
    stage 0, so dropping it into the tray never costs a stage. Stages 1 and 2 need ``held_closed``, so a wedge of
    the open fingers earns nothing; ``grasped`` stays the original report's contact-only event for its terms.
    Why each rule (what PPO and SAC learned without it): docs/reward_design.md, "TableClearing's staged reward".

    **Episode length:** 250 control steps (12.5 s at 20 Hz). The scripted expert needs about 75;
    the original report allowed 3000 actions of a much slower loop. 250 leaves 2.5x margin for learners without
    letting a stuck policy waste long rollouts.
    """

    EPISODE_STATE = ("obj_start_pos",)  # the approach term stops paying once the object moved from here

    # ------------------------------------------------------------------ scene and episodes
    def _load_scene(self, options: dict):
        self.build_trays()
        self.obj = self.target_object = self._build_object("object", [0.8, 0.1, 0.1, 1])
        self.build_background()
        self.watch_contacts([self.obj])
        with torch.device(self.device):
            self.dest_center = torch.tensor([*DEST_TRAY_XY, TRAY_FLOOR_TOP]).repeat(self.num_envs, 1)
            self.obj_start_pos = torch.zeros(self.num_envs, 3)

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        u = self._episode_draws(env_idx, joint_noise=6, obj_xy=2, obj_yaw=1)
        self._reset_robot(env_idx, u["joint_noise"])
        pose = self._spawn_in_source_tray(u["obj_xy"], u["obj_yaw"])
        self.obj.set_pose(pose)
        self.obj_start_pos[env_idx] = pose.p

    # ------------------------------------------------------------------ evaluation
    def privileged_state(self) -> dict[str, torch.Tensor]:
        return dict(obj_pose=raw_pose(self.obj))

    def _inside_dest_xy(self, p: torch.Tensor) -> torch.Tensor:
        return ((p[:, :2] - self.dest_center[:, :2]).abs() < TRAY_INNER / 2).all(dim=1)

    def evaluate(self) -> dict:
        """Events and all reward terms. Idempotent between steps (see ``_previous``)."""
        state = self._read_step_state()
        obj_p, tcp_p = state["obj_pose"][:, :3], state["tcp_pose"][:, :3]
        contacts = self.contacts.flags()
        robot_hit, forces = contacts.robot_hit, contacts.finger_forces[0]

        lifted = obj_p[:, 2] - self.source_center[:, 2] >= GRASP_LIFT
        # the original report's grasp (its reward terms read it): finger contacts only, whatever the command
        held = self._grasped(forces, state["tcp_pose"][:, 3:], closed=False) & ~contacts.object_hit[0]
        held_closed = held & self.agent.gripper_commanded_closed  # the staged reward's grasp: no wedge
        grasped = held & lifted
        over_dest = self._inside_dest_xy(obj_p)
        in_dest = over_dest & (obj_p[:, 2] < self.dest_center[:, 2] + TRAY_WALL_H)
        delivered = in_dest & ~self._touches(forces)
        cur = dict(
            tcp_obj_dist=torch.linalg.norm(obj_p - tcp_p, dim=1),
            tcp_dest_dist=torch.linalg.norm(self.dest_center - tcp_p, dim=1),
            grasped=grasped,
            delivered=delivered,
        )
        prev = self._previous(cur)

        zeros = torch.zeros_like(cur["tcp_obj_dist"])
        moved = torch.linalg.norm(obj_p - self.obj_start_pos, dim=1) >= APPROACH_MOVE_LIMIT
        closer = cur["tcp_obj_dist"] < prev["tcp_obj_dist"]
        closer_dest = cur["tcp_dest_dist"] < prev["tcp_dest_dist"]
        # nothing happens "during" a reset (unconditional: testing fresh.any() would wait for the GPU)
        moving = ~self._fresh
        r_approach = torch.where(moving & ~grasped & ~moved, torch.where(closer, R_APPROACH, -R_APPROACH), zeros)
        r_carry = torch.where(moving & grasped, torch.where(closer_dest, R_CARRY, -R_CARRY), zeros)
        dropped = prev["grasped"] & ~grasped & ~over_dest
        return dict(
            **self._common_info(robot_hit, grasped),
            success=delivered,
            dropped=dropped,
            delivered=delivered,
            object_lifted=lifted,
            object_over_dest=over_dest,
            object_in_dest=in_dest,
            held=held,
            held_closed=held_closed,
            r_approach=r_approach,
            r_carry=r_carry,
            r_time=torch.full_like(zeros, R_TIME),
            r_collision=torch.where(robot_hit, R_COLLISION, zeros),
            r_grasp=torch.where(grasped & ~prev["grasped"], R_GRASP, zeros),
            r_drop=torch.where(dropped, R_DROP, zeros),
            r_delivery=torch.where(delivered & ~prev["delivered"], R_DELIVERY, zeros),
        )

    # ------------------------------------------------------------------ observations
    def state_observations(self, state: dict[str, torch.Tensor], info: dict) -> dict[str, torch.Tensor]:
        obj, tcp = state["obj_pose"], state["tcp_pose"]
        return dict(
            obj_pose=obj.clone(),
            source_tray_pos=self.source_center.clone(),
            dest_tray_pos=self.dest_center.clone(),
            tcp_to_obj_pos=obj[:, :3] - tcp[:, :3],
            tcp_to_obj_yaw=step_grasp_yaw_error(state, "obj_pose")[:, None],
            obj_to_dest_pos=self.dest_center - obj[:, :3],
        )

    # ------------------------------------------------------------------ rewards
    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """The original report's reward: the sum of its terms (-1000 per collision)."""
        return sum(info[k] for k in REWARD_TERMS)

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """Staged reward in [0, 1] (the default mode, for ManiSkill's PPO), stage k paying (k + progress) / 4
        with progress in [0, 1) (the table in the class docstring). Not the dense reward (that is the original
        report's), so this one is the task's own rather than the base's dense / MAX_STAGED_REWARD."""
        obj_p = self.step_state["obj_pose"][:, :3]
        reach = grasp_approach_reward(
            self.step_state["obj_pose"], self.tcp_pose, step_grasp_yaw_error(self.step_state, "obj_pose")
        )
        lift = ((obj_p[:, 2] - self.source_center[:, 2]) / GRASP_LIFT).clamp(0, 0.999)
        goal = self.dest_center + up(self.object_half_size, obj_p)
        place = reach_reward(torch.linalg.norm(goal - obj_p, dim=1)).clamp(max=0.999)
        reward = torch.where(info["held_closed"], 1 + lift, reach)
        reward = torch.where(info["held_closed"] & info["object_lifted"], 2 + place, reward)
        # over the destination tray, held, falling or let go inside it: opening the fingers there, at any height,
        # is no step down, and holding on is worth at most three quarters of the band, a quarter of it for
        # commanding "open" (only a hold or a grasp brings the object here; an object resting on one finger above
        # the tray is not delivered, and pays no more than the place it has not reached)
        release = (torch.as_tensor(action, device=place.device)[:, -1].clamp(-1, 1) + 1) / 2
        held_place = (HELD_PLACE_SHARE + RELEASE_SHARE * release) * place
        reward = torch.where(info["object_over_dest"], 3 + torch.where(info["held"], held_place, place), reward)
        reward = torch.where(info["success"], self.MAX_STAGED_REWARD, reward)
        reward = torch.where(info["fail"], 0.0, reward)
        return reward / self.MAX_STAGED_REWARD
