"""TableClearing-IRB120-v1: move an object from the yellow source tray to the green destination tray.

The scene, events and dense reward follow the seed design. The robot stands directly on the table
top (robot root at world z = 0 = table top) and the two trays sit in front of it (+x) at
(0.35, +0.13) (source) and (0.35, -0.13) (destination), 16 x 16 cm inside, which the IRB 120 reaches
everywhere with the gripper pointing down (checked with the IK in ``tests/test_table_clearing.py``).

Everything is batched over ``(num_envs, ...)`` torch tensors so the task runs on ``physx_cpu``
(num_envs=1) and ``physx_cuda`` alike.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import sapien
import torch
from gymnasium.utils import seeding as gym_seeding
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.envs.utils.observations import ALL_VISUAL_TEXTURES, parse_obs_mode_to_struct
from mani_skill.sensors.camera import Camera, CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.actor import Actor
from mani_skill.utils.structs.pose import Pose

from maniskill_irb120.agents.irb120 import IRB120Metalwork
from maniskill_irb120.contract import as_action_array, check_env_idx
from maniskill_irb120.robot_description import merged_box_mesh

# --------------------------------------------------------------------------- scene geometry (metres)
TABLE_SIZE = (1.2, 1.0, 0.75)  # x, y, height; the top is at world z = 0
TABLE_CENTER_XY = (0.3, 0.0)  # reaches 0.3 m behind the robot root so the base stands on it
TRAY_INNER = 0.16  # inner side length of both (square) trays
TRAY_WALL_T = 0.005  # wall and floor thickness
TRAY_WALL_H = 0.03  # wall height above the tray floor's top surface
SOURCE_TRAY_XY = (0.35, 0.13)
DEST_TRAY_XY = (0.35, -0.13)
TRAY_FLOOR_TOP = TRAY_WALL_T  # trays stand on the table (z = 0)
SPAWN_MARGIN = 0.03  # object centre keeps this distance from the inner walls

# --------------------------------------------------------------------------- events and rewards
GRASP_LIFT = 0.05  # "grasped" needs the object centre >= 5 cm above the source tray floor
APPROACH_MOVE_LIMIT = 0.05  # the approach term is active only until the object moved this far
CONTACT_FORCE_EPS = 1e-2  # N; a robot link pressing on the scene harder than this is a collision
R_APPROACH, R_CARRY, R_TIME = 1.0, 1.0, -1.0
R_COLLISION, R_GRASP, R_DROP, R_DELIVERY = -1000.0, 100.0, -200.0, 200.0
VIDEO_BLOCK = 16  # render_mode="all" frames are padded to multiples of this (video encoders' macro block)
REWARD_TERMS = ("r_approach", "r_carry", "r_time", "r_collision", "r_grasp", "r_drop", "r_delivery")


@register_env("TableClearing-IRB120-v1", max_episode_steps=250)
class TableClearingIRB120Env(BaseEnv):
    """Pick the object in the yellow tray and release it inside the green tray.

    **Randomisation:** the object's centre is uniform in the source tray's inner square shrunk by
    ``spawn_margin`` (3 cm) and its yaw is uniform in [0, 2π). It is spawned *resting* on the tray
    floor rather than dropped from a few cm as in the seed: ManiSkill's ``_initialize_episode`` cannot
    step physics, and a falling object at t = 0 would make the first steps' rewards depend on the
    settling transient. The robot starts at the ``rest`` keyframe plus optional uniform joint noise
    ``robot_init_qpos_noise`` (default 0).

    **Events** (all ``(N,)`` bool in ``info``):

    - ``grasped``: both fingers squeeze the object (``agent.is_grasping``), nothing but the robot
      touches it, and its centre is >= 5 cm above the source tray floor (the seed's definition).
    - ``collided`` (= ``fail``): a robot link other than ``base_link`` (which stands on the table)
      pushes on the table, a tray or the ground with more than 0.01 N.
    - ``dropped``: grasped at t-1, not at t, and the object's centre is not over the destination
      tray's inner square.
    - ``delivered`` (= ``success``): the object's centre is over the destination tray's inner square,
      below its wall top and touches neither finger, i.e. it was released in the tray. The seed only
      said "reached the destination tray"; requiring the release keeps a held object from counting.

    **Dense reward** (the seed's terms, each also in ``info``): approach ±1 while not grasped and
    the object is within 5 cm of its start (+1 if the TCP got closer to it); carry ±1 while grasped
    (+1 if the TCP got closer to the destination tray centre); time -1; collision -1000; grasp +100
    on the not-grasped → grasped edge; drop -200; delivery +200 on the not-delivered → delivered edge.

    **Episode length:** 250 control steps (12.5 s at 20 Hz). The scripted expert needs about 100;
    the seed allowed 3000 actions of a much slower loop. 250 leaves 2.5x margin for learners without
    letting a stuck policy waste long rollouts.
    """

    SUPPORTED_ROBOTS = ["irb120_metalwork"]
    # the first is the default (BaseEnv takes SUPPORTED_REWARD_MODES[0]): normalized_dense, as in ManiSkill's own
    # tasks, whose PPO examples pass no reward_mode; the seed's reward (-1000 per collision) is reward_mode="dense"
    SUPPORTED_REWARD_MODES = ["normalized_dense", "dense", "sparse", "none"]
    agent: IRB120Metalwork

    def __init__(
        self,
        *args,
        robot_uids: str = "irb120_metalwork",
        obs_mode: str = "rgbd",
        reward_mode: str | None = None,
        control_mode: str | None = None,
        robot_init_qpos_noise: float = 0.0,
        object_half_size: float = 0.01,
        object_mass: float = 0.02,
        object_friction: float = 1.0,
        spawn_margin: float = SPAWN_MARGIN,
        enhanced_determinism: bool = True,
        **kwargs,
    ):
        """``enhanced_determinism`` defaults to True (ManiSkill's default is False) so that an
        unseeded ``reset()`` after ``reset(seed=s)`` draws its episode seed from the seeded main RNG:
        the gymnasium contract (and its env checker) expects that sequence to be reproducible."""
        if robot_uids not in self.SUPPORTED_ROBOTS:
            raise ValueError(f"robot_uids={robot_uids!r} is not supported; use one of {self.SUPPORTED_ROBOTS}")
        if reward_mode is not None and reward_mode not in self.SUPPORTED_REWARD_MODES:
            raise ValueError(f"reward_mode={reward_mode!r} is not supported; use one of {self.SUPPORTED_REWARD_MODES}")
        self._check_obs_mode(obs_mode)
        self._check_batching(kwargs.get("num_envs", args[0] if args else 1), kwargs.get("sim_backend", "auto"))
        if not 0.003 <= object_half_size <= 0.012:
            raise ValueError(
                f"object_half_size={object_half_size} m: the open gripper (26 mm gap) holds cubes of "
                "half size 3..12 mm (the 2 mm closed gap cannot squeeze smaller ones)"
            )
        if object_mass <= 0 or object_friction < 0:
            raise ValueError(f"object_mass={object_mass} must be > 0 and object_friction={object_friction} >= 0")
        if not 0 <= spawn_margin < TRAY_INNER / 2:
            raise ValueError(f"spawn_margin={spawn_margin} must be in [0, {TRAY_INNER / 2})")
        self.robot_init_qpos_noise = robot_init_qpos_noise
        self.object_half_size = object_half_size
        self.object_mass = object_mass
        self.object_friction = object_friction
        self.spawn_margin = spawn_margin
        super().__init__(
            *args, robot_uids=robot_uids, obs_mode=obs_mode, reward_mode=reward_mode,
            control_mode=control_mode, enhanced_determinism=enhanced_determinism, **kwargs,
        )

    # ------------------------------------------------------------------ cameras
    @property
    def _default_sensor_configs(self):
        """No scene cameras: the policy sees only the agent's 84x84 hand camera, as in the seed. Every
        extra sensor would be rendered each step (and concatenated by ManiSkill's RGB-D flattening)."""
        return []

    @property
    def _default_human_render_camera_configs(self):
        """Overview of robot and both trays for videos; rendered only on ``env.render()``."""
        pose = sapien_utils.look_at(eye=[0.95, 0.55, 0.6], target=[0.2, 0.0, 0.08])
        return CameraConfig("render_camera", pose, 512, 512, 1.0, 0.01, 10)

    # ------------------------------------------------------------------ scene
    def _load_agent(self, options: dict):
        # robot root on the table top at the world origin; the trays are in front (+x)
        try:
            super()._load_agent(options, sapien.Pose(p=[0.0, 0.0, 0.0]))
        except AssertionError as e:  # BaseAgent asserts on an unknown control mode; say so clearly
            if self._control_mode is not None and "not in supported modes" in str(e):
                raise ValueError(f"control_mode={self._control_mode!r} is not supported: {e}") from None
            raise

    def _build_box_actor(self, name: str, boxes: list[tuple[tuple, tuple]], color, xy=(0.0, 0.0)) -> Actor:
        """A static actor made of (half_size, centre) boxes: box collisions, one merged visual mesh
        (one draw call instead of one per box)."""
        builder = self.scene.create_actor_builder()
        for half, centre in boxes:
            builder.add_box_collision(pose=sapien.Pose(p=list(centre)), half_size=list(half))
        builder.add_visual_from_file(merged_box_mesh(boxes), material=sapien.render.RenderMaterial(base_color=color))
        builder.initial_pose = sapien.Pose(p=[xy[0], xy[1], 0.0])
        return builder.build_static(name=name)

    def _build_tray(self, name: str, xy, color) -> Actor:
        """Open box: floor + 4 walls (5 boxes) resting on the table, inner size TRAY_INNER²."""
        t, h, a = TRAY_WALL_T, TRAY_WALL_H, TRAY_INNER / 2
        wall_z = t + h / 2
        outer = a + t
        boxes = [
            ((outer, outer, t / 2), (0.0, 0.0, t / 2)),  # floor
            ((t / 2, outer, h / 2), (a + t / 2, 0.0, wall_z)),  # +x wall
            ((t / 2, outer, h / 2), (-a - t / 2, 0.0, wall_z)),  # -x wall
            ((a, t / 2, h / 2), (0.0, a + t / 2, wall_z)),  # +y wall
            ((a, t / 2, h / 2), (0.0, -a - t / 2, wall_z)),  # -y wall
        ]
        return self._build_box_actor(name, boxes, color, xy)

    def _build_floor(self, altitude: float, half_width: float = 4.0) -> Actor:
        """A collision plane with one flat-coloured quad box: ManiSkill's ``build_ground`` draws a
        textured grid that costs ~0.7 ms per 84x84 frame on the CPU rasteriser, a third of the render."""
        builder = self.scene.create_actor_builder()
        builder.add_plane_collision(sapien.Pose(p=[0, 0, altitude], q=[0.7071068, 0, -0.7071068, 0]))
        builder.add_box_visual(pose=sapien.Pose(p=[0, 0, altitude - 0.005]), half_size=[half_width, half_width, 0.005],
                               material=sapien.render.RenderMaterial(base_color=[0.45, 0.47, 0.5, 1.0]))
        builder.initial_pose = sapien.Pose()
        return builder.build_static(name="ground")

    def _load_scene(self, options: dict):
        sx, sy, sz = TABLE_SIZE
        self.source_tray = self._build_tray("source_tray", SOURCE_TRAY_XY, [0.95, 0.8, 0.1, 1.0])
        self.dest_tray = self._build_tray("dest_tray", DEST_TRAY_XY, [0.1, 0.7, 0.2, 1.0])

        h = self.object_half_size
        builder = self.scene.create_actor_builder()
        phys_mat = sapien.pysapien.physx.PhysxMaterial(
            static_friction=self.object_friction, dynamic_friction=self.object_friction, restitution=0.0
        )
        builder.add_box_collision(half_size=[h] * 3, material=phys_mat, density=self.object_mass / (2 * h) ** 3)
        builder.add_box_visual(half_size=[h] * 3, material=sapien.render.RenderMaterial(base_color=[0.8, 0.1, 0.1, 1]))
        builder.initial_pose = sapien.Pose(p=[*SOURCE_TRAY_XY, TRAY_FLOOR_TOP + h])
        self.obj = builder.build(name="object")
        # big background surfaces last: drawn after what covers them, most of their pixels fail the
        # rasteriser's early depth test (build order is draw order; measured 2.25 -> 1.4 ms per frame)
        self.table = self._build_box_actor(
            "table", [((sx / 2, sy / 2, sz / 2), (TABLE_CENTER_XY[0], TABLE_CENTER_XY[1], -sz / 2))],
            [0.55, 0.42, 0.3, 1.0],
        )
        self.ground = self._build_floor(altitude=-sz)

        self.scene_actors = [self.table, self.source_tray, self.dest_tray, self.ground]
        self.robot_links = [l for l in self.agent.robot.links if l.name != "base_link"]
        self.fingers = [self.agent.finger_left, self.agent.finger_right]
        self._entity_kind = None  # CPU contact lookup, rebuilt for each new scene

        with torch.device(self.device):
            n = self.num_envs
            self.source_center = torch.tensor([*SOURCE_TRAY_XY, TRAY_FLOOR_TOP]).repeat(n, 1)
            self.dest_center = torch.tensor([*DEST_TRAY_XY, TRAY_FLOOR_TOP]).repeat(n, 1)
            self.obj_start_pos = torch.zeros(n, 3)
            # previous-step values for the edge-triggered events and the ±1 shaping terms
            self._cur = self._blank_state(n)
            self._prev = self._blank_state(n)
            self._fresh = torch.ones(n, dtype=torch.bool)

    @staticmethod
    def _blank_state(n: int) -> dict[str, torch.Tensor]:
        return dict(
            tcp_obj_dist=torch.zeros(n),
            tcp_dest_dist=torch.zeros(n),
            grasped=torch.zeros(n, dtype=torch.bool),
            delivered=torch.zeros(n, dtype=torch.bool),
        )

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | list[int] | None = None, options: dict | None = None):
        """ManiSkill's reset, plus gymnasium's ``np_random`` seeded alike (ManiSkill keeps its own RNGs
        and never seeds it, which gymnasium's env checker and ``Env.np_random`` users expect)."""
        self._check_open()
        options = self._checked_reset_options(options)
        if seed is not None:
            first = int(seed[0]) if np.iterable(seed) else int(seed)
            self._np_random, self._np_random_seed = gym_seeding.np_random(first)
        return super().reset(seed=seed, options=options)

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        self._captured_ahead = False  # a reset's observation is always captured afresh
        with torch.device(self.device):
            b = len(env_idx)
            qpos = torch.as_tensor(self.agent.keyframes["rest"].qpos, dtype=torch.float32).repeat(b, 1)
            if self.robot_init_qpos_noise > 0:
                qpos[:, :6] += (torch.rand(b, 6) * 2 - 1) * self.robot_init_qpos_noise
            self.agent.reset(qpos)
            self.agent.robot.set_pose(sapien.Pose())

            h = self.object_half_size
            span = TRAY_INNER / 2 - self.spawn_margin
            xyz = torch.zeros(b, 3)
            xyz[:, :2] = (torch.rand(b, 2) * 2 - 1) * span + torch.tensor(SOURCE_TRAY_XY)
            xyz[:, 2] = TRAY_FLOOR_TOP + h
            yaw = torch.rand(b) * 2 * np.pi
            q = torch.zeros(b, 4)
            q[:, 0] = torch.cos(yaw / 2)
            q[:, 3] = torch.sin(yaw / 2)
            self.obj.set_pose(Pose.create_from_pq(xyz, q))
            self.obj_start_pos[env_idx] = xyz
            self._fresh[env_idx] = True

    def _before_control_step(self):
        """The state evaluated after the last step (or reset) becomes the reference for this step."""
        self._prev = {k: v.clone() for k, v in self._cur.items()}
        self._fresh[:] = False

    render_ahead: bool = True
    _captured_ahead: bool = False

    def _after_control_step(self):
        """Start this step's camera frame now, before ``evaluate``: on the CPU the rasteriser draws it in
        its own threads while this thread evaluates the step, and ``get_obs`` then only reads it back
        (measured: ~1 ms less per rgbd step on 2 cores). The scene does not change in between, so the
        images are the ones ManiSkill's capture in ``get_obs`` takes (tested). GPU sim: ManiSkill's path."""
        if (not self.render_ahead or self.gpu_sim_enabled or not self._sensors
                or self._obs_mode in ("state", "state_dict", "none")):
            return
        for obj in self._hidden_objects:
            obj.hide_visual()
        self.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        self.capture_sensor_data()
        self._captured_ahead = True

    def _get_obs_sensor_data(self, apply_texture_transforms: bool = True) -> dict:
        if not self._captured_ahead:
            return super()._get_obs_sensor_data(apply_texture_transforms)
        # the frame is in flight: read it back without ManiSkill's update_render + capture (a second
        # update would only mark the pictures stale); otherwise as ManiSkill 3.0.1's method does
        self._captured_ahead = False
        v = self.obs_mode_struct.visual
        return {
            name: sensor.get_obs(rgb=v.rgb, depth=v.depth, position=v.position, segmentation=v.segmentation,
                                 normal=v.normal, albedo=v.albedo, apply_texture_transforms=apply_texture_transforms)
            if isinstance(sensor, Camera) else sensor.get_obs()
            for name, sensor in self.scene.sensors.items()
        }

    # ------------------------------------------------------------------ contacts
    def _contact_flags(self) -> tuple[torch.Tensor, ...]:
        """Contacts of this step, all batched (N,...):

        (robot touches the scene, object touches the scene, object touches a finger,
        force on the left finger from the object (N,3), same for the right finger).

        The scene is the table, both trays and the ground; base_link is excluded because it stands on
        the table. GPU: ManiSkill's batched pairwise queries. CPU: one pass over PhysX's contact list
        instead of 40+ pairwise queries that each rescan it (same answer, see the tests).
        """
        if self.gpu_sim_enabled:
            return self._contact_flags_pairwise()
        return self._contact_flags_cpu()

    def _contact_flags_pairwise(self) -> tuple[torch.Tensor, ...]:
        f = self.scene.get_pairwise_contact_forces
        robot_hit = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        obj_hit = torch.zeros_like(robot_hit)
        for a in self.scene_actors:
            for link in self.robot_links:
                robot_hit |= torch.linalg.norm(f(link, a), dim=1) > CONTACT_FORCE_EPS
            obj_hit |= torch.linalg.norm(f(self.obj, a), dim=1) > CONTACT_FORCE_EPS
        lf, rf = f(self.fingers[0], self.obj), f(self.fingers[1], self.obj)
        finger = (torch.linalg.norm(lf, dim=1) > CONTACT_FORCE_EPS) | (torch.linalg.norm(rf, dim=1) > CONTACT_FORCE_EPS)
        return robot_hit, obj_hit, finger, lf, rf

    def _contact_flags_cpu(self) -> tuple[torch.Tensor, ...]:
        if self._entity_kind is None:
            kind = {}
            for a in self.scene_actors:
                kind[a._bodies[0].entity] = "scene"
            for link in self.robot_links:
                kind[link._bodies[0].entity] = "robot"
            for i, link in enumerate(self.fingers):
                kind[link._bodies[0].entity] = f"finger{i}"
            kind[self.obj._bodies[0].entity] = "obj"
            self._entity_kind = kind
        kind = self._entity_kind
        dt = self.scene.px.timestep
        robot_hit = obj_hit = False
        finger_impulse = [np.zeros(3), np.zeros(3)]
        eps_impulse_sq = (CONTACT_FORCE_EPS * dt) ** 2
        for c in self.scene.px.get_contacts():
            k0, k1 = kind.get(c.bodies[0].entity), kind.get(c.bodies[1].entity)
            if k0 is None or k1 is None or k0 == k1:
                continue
            pair = {k0, k1}
            if "scene" not in pair and "obj" not in pair:
                continue
            impulse = sum(p.impulse for p in c.points) if c.points else np.zeros(3)
            if "obj" in pair and (k0[0] == "f" or k1[0] == "f"):
                # impulse on the finger from the object, with ManiSkill's pairwise sign convention
                if k0 == "obj":
                    finger_impulse[int(k1[-1])] -= impulse
                else:
                    finger_impulse[int(k0[-1])] += impulse
                continue
            if float(impulse @ impulse) <= eps_impulse_sq:
                continue
            if "scene" in pair and ("robot" in pair or "finger0" in pair or "finger1" in pair):
                robot_hit = True
            elif pair == {"obj", "scene"}:
                obj_hit = True
        forces = torch.from_numpy(np.stack(finger_impulse).astype(np.float32) / dt).to(self.device)
        touch = max(float(f @ f) for f in finger_impulse) > eps_impulse_sq
        flags = torch.tensor([[robot_hit], [obj_hit], [touch]], device=self.device)
        return flags[0], flags[1], flags[2], forces[0:1], forces[1:2]

    # ------------------------------------------------------------------ evaluation
    def _inside_dest_xy(self, p: torch.Tensor) -> torch.Tensor:
        d = (p[:, :2] - self.dest_center[:, :2]).abs()
        return (d < TRAY_INNER / 2).all(dim=1)

    def evaluate(self) -> dict:
        """Events and all reward terms. Idempotent between steps: the reference state is snapshotted
        in ``_before_control_step``, so calling this twice gives the same answer."""
        # fetched once per step: observations and rewards of this step read the same poses
        self._obj_pose, self._tcp_pose = self.obj.pose.raw_pose, self.agent.tcp_pose.raw_pose
        obj_p, tcp_p = self._obj_pose[:, :3], self._tcp_pose[:, :3]
        robot_hit, obj_hit, finger_touch, lf, rf = self._contact_flags()

        lifted = obj_p[:, 2] - self.source_center[:, 2] >= GRASP_LIFT
        grasped = self.agent.is_grasping(self.obj, finger_forces=(lf, rf), tcp_quat=self._tcp_pose[:, 3:]) & ~obj_hit & lifted
        over_dest = self._inside_dest_xy(obj_p)
        delivered = over_dest & (obj_p[:, 2] < self.dest_center[:, 2] + TRAY_WALL_H) & ~finger_touch
        cur = dict(
            tcp_obj_dist=torch.linalg.norm(obj_p - tcp_p, dim=1),
            tcp_dest_dist=torch.linalg.norm(self.dest_center - tcp_p, dim=1),
            grasped=grasped,
            delivered=delivered,
        )
        fresh = self._fresh
        prev = {k: torch.where(fresh, cur[k], self._prev[k]) for k in cur}
        self._cur = cur

        ones = torch.ones_like(cur["tcp_obj_dist"])
        zeros = torch.zeros_like(ones)
        moved = torch.linalg.norm(obj_p - self.obj_start_pos, dim=1) >= APPROACH_MOVE_LIMIT
        closer = cur["tcp_obj_dist"] < prev["tcp_obj_dist"]
        r_approach = torch.where(~grasped & ~moved, torch.where(closer, ones, -ones) * R_APPROACH, zeros)
        closer_dest = cur["tcp_dest_dist"] < prev["tcp_dest_dist"]
        r_carry = torch.where(grasped, torch.where(closer_dest, ones, -ones) * R_CARRY, zeros)
        grasp_event = grasped & ~prev["grasped"]
        dropped = prev["grasped"] & ~grasped & ~over_dest
        delivery_event = delivered & ~prev["delivered"]
        if bool(fresh.any()):  # nothing happens "during" a reset
            r_approach = torch.where(fresh, zeros, r_approach)
            r_carry = torch.where(fresh, zeros, r_carry)
        return dict(
            success=delivered,
            fail=robot_hit,
            grasped=grasped,
            is_grasped=grasped,
            dropped=dropped,
            collided=robot_hit,
            delivered=delivered,
            object_lifted=lifted,
            object_over_dest=over_dest,
            ik_unreachable=self.agent.ik_unreachable.clone(),
            r_approach=r_approach,
            r_carry=r_carry,
            r_time=ones * R_TIME,
            r_collision=torch.where(robot_hit, R_COLLISION, zeros),
            r_grasp=torch.where(grasp_event, R_GRASP, zeros),
            r_drop=torch.where(dropped, R_DROP, zeros),
            r_delivery=torch.where(delivery_event, R_DELIVERY, zeros),
        )

    # ------------------------------------------------------------------ observations
    def _get_obs_extra(self, info: dict):
        """Copies, never the env's own tensors: a caller writing into an observation (``state_dict``) must not
        move the trays the env scores against, nor change ``info`` or the next step's grasp edge."""
        obs = dict(tcp_pose=self._tcp_pose.clone(), is_grasped=info["grasped"].clone())
        if self.obs_mode_struct.use_state:
            obs.update(
                obj_pose=self._obj_pose.clone(),
                source_tray_pos=self.source_center.clone(),
                dest_tray_pos=self.dest_center.clone(),
                tcp_to_obj_pos=self._obj_pose[:, :3] - self._tcp_pose[:, :3],
                obj_to_dest_pos=self.dest_center - self._obj_pose[:, :3],
            )
        return obs

    # ------------------------------------------------------------------ rewards
    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return sum(info[k] for k in REWARD_TERMS)

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """Staged reward in [0, 1] for ManiSkill's PPO baseline: reach, grasp, bring over the
        destination tray, release in it (1.0). A collision scores 0."""
        obj_p = self._obj_pose[:, :3]
        grasped = info["grasped"].float()
        reach = 1 - torch.tanh(5 * torch.linalg.norm(obj_p - self._tcp_pose[:, :3], dim=1))
        goal = self.dest_center.clone()
        goal[:, 2] += self.object_half_size
        place = 1 - torch.tanh(5 * torch.linalg.norm(goal - obj_p, dim=1))
        reward = torch.where(info["grasped"], torch.ones_like(reach), reach) + grasped + grasped * place
        reward = torch.where(info["success"], torch.full_like(reward, 4.0), reward)
        reward = torch.where(info["fail"], torch.zeros_like(reward), reward)
        return reward / 4.0

    def compute_sparse_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return info["success"].float()

    # ------------------------------------------------------------------ input checks (the env contract)
    def step(self, action: Any):
        """ManiSkill's step, for lists and tuples of numbers too: BaseEnv takes only arrays, tensors and dicts
        and raises a bare ``TypeError: <class 'list'>``. Strings and other objects get a TypeError naming them."""
        self._check_open()
        if action is not None and not isinstance(action, dict):
            action = as_action_array(action)
        return super().step(action)

    _closed: bool = False

    def close(self):
        self._closed = True
        super().close()

    def render(self):
        self._check_open()
        return super().render()

    def render_all(self):
        """ManiSkill's overview + hand-camera composite (512 x 596 by default) padded with black on the right
        and bottom to multiples of 16: video encoders (imageio/ffmpeg, macro_block_size 16) would otherwise
        rescale every frame, with a warning."""
        img = super().render_all()
        h, w = img.shape[-3], img.shape[-2]
        ph, pw = -h % VIDEO_BLOCK, -w % VIDEO_BLOCK
        if not ph and not pw:
            return img
        pad = [(0, 0)] * (img.ndim - 3) + [(0, ph), (0, pw), (0, 0)]
        if isinstance(img, torch.Tensor):
            return torch.nn.functional.pad(img, [p for pair in reversed(pad) for p in pair])
        return np.pad(img, pad)

    def _check_open(self) -> None:
        """After ``close()`` ManiSkill has dropped the scene and agent: say so instead of failing on ``None``."""
        if self._closed:
            raise RuntimeError("the env is closed; make a new one with gym.make(...)")

    # obs modes ManiSkill 3.0.1 accepts by name: its SUPPORTED_OBS_MODES lacks "rgbd" and the single textures,
    # which parse_obs_mode_to_struct handles ("any_textures" there is a flag, not a mode)
    NAMED_OBS_MODES = ("rgbd", "state", "state_dict", "none", "sensor_data", "pointcloud", *ALL_VISUAL_TEXTURES)

    @classmethod
    def _check_obs_mode(cls, obs_mode: str | None) -> None:
        """ValueError listing every valid mode: ManiSkill asserts, or fails on ``str.split``, deep in its init."""
        if obs_mode is None or obs_mode in cls.NAMED_OBS_MODES:
            return
        try:  # combinations such as "rgb+depth" or "rgb+state_dict" (ManiSkill asserts on bad ones)
            if isinstance(obs_mode, str) and obs_mode:
                parse_obs_mode_to_struct(obs_mode)
                return
        except AssertionError:
            pass
        raise ValueError(
            f"obs_mode={obs_mode!r} is not supported; use one of {list(cls.NAMED_OBS_MODES)} or a '+'-joined "
            f"combination of {ALL_VISUAL_TEXTURES} with optional 'state' / 'state_dict', e.g. 'rgb+depth+state'"
        )

    @staticmethod
    def _check_batching(num_envs: Any, sim_backend: str) -> None:
        """Clear errors for ``num_envs``: ManiSkill fails on 0 with a bare IndexError, and on num_envs > 1
        without CUDA with ``failed to find device "cuda"``, which does not say that CPUs need worker processes."""
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if num_envs == 1:
            return
        on_gpu = sim_backend == "auto" or "cuda" in str(sim_backend) or sim_backend == "gpu"
        if not on_gpu or not torch.cuda.is_available():
            why = f"sim_backend={sim_backend!r} was given" if not on_gpu else "no CUDA GPU is available here"
            raise ValueError(
                f"num_envs={num_envs}: batched envs (num_envs > 1) need a CUDA GPU (sim_backend='physx_cuda'), and "
                f"{why}. On CPUs use maniskill_irb120.make_vec_env(env_id, num_envs, backend=\"cpu\"): one worker "
                "process per env behind the same batched interface."
            )

    def _checked_reset_options(self, options: dict | None) -> dict | None:
        """``options["env_idx"]`` checked (ValueError naming the valid range instead of a bare IndexError) and
        handed on as an index tensor on the env's device."""
        if options is None:
            return None
        if not isinstance(options, dict):
            raise TypeError(f"reset options must be a dict, got {type(options).__name__}")
        if "env_idx" not in options:
            return options
        idx = check_env_idx(options["env_idx"], self.num_envs)
        return {**options, "env_idx": torch.as_tensor(idx, device=self.device)}
