"""What every IRB 120 table task shares, so that a task file holds only its own logic (like ManiSkill's
``pick_cube.py``): argument checks, cameras, the robot on the table, per-env episode randomness, the
shared scene and contacts, edge-triggered events, render-ahead on the CPU and state restore.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import sapien
import torch
from gymnasium.utils import seeding as gym_seeding
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.structs.actor import Actor
from mani_skill.utils.structs.pose import Pose

from maniskill_irb120.envs.contract import EnvContractMixin
from maniskill_irb120.envs.randomization import RandomizationMixin
from maniskill_irb120.envs.scene import (
    CONTACT_FORCE_EPS,
    SOURCE_TRAY_XY,
    SPAWN_MARGIN,
    TRAY_FLOOR_TOP,
    TRAY_INNER,
    Contacts,
    TableScene,
    build_object,
    check_object_params,
)
from maniskill_irb120.errors import UsageError
from maniskill_irb120.maniskill_compat import (
    episode_reset,
    raw_pose,
    read_sensor_obs,
    reset_mask_from_options,
    restore_controller_state,
    state_extras,
)
from maniskill_irb120.robot.irb120 import IRB120Metalwork

# the first is the default (BaseEnv takes SUPPORTED_REWARD_MODES[0]): normalized_dense, as in ManiSkill's own tasks,
# whose PPO examples pass no reward_mode; TableClearing's original reward (-1000 per collision) is reward_mode="dense"
REWARD_MODES = ["normalized_dense", "dense", "sparse", "none"]

REACH_SCALE = 3.0
"""k of the staged rewards' reach term 1 - tanh(k·d). ManiSkill uses 5; here the TCP starts 0.3-0.35 m from the
object, where 5 is nearly flat (slope 0.6 per m at 0.35 m); 3 doubles the slope there (1.2 per m; the
largest slope at the start is k·d ≈ 0.8) and still gives 3 per m at the object."""
ALIGN_SCALE = 40.0
"""k of :func:`grasp_approach_reward`'s millimetre terms 1 - tanh(k·d): 4 mm off pays 0.85, 12 mm 0.55."""
GRASP_POINT_OFFSET = 0.005
"""m: the TCP above the object's centre at a grasp (the expert's ``grasp_offset``: finger tips below the centre,
the gripper body above the tray walls)."""


class IRB120TableEnv(EnvContractMixin, RandomizationMixin, BaseEnv):
    """Base of the IRB 120 table tasks. Subclasses implement ManiSkill's ``_load_scene``,
    ``_initialize_episode``, ``evaluate`` and ``compute_dense_reward``, and declare what other layers may read:
    ``target_object``, :meth:`privileged_state` and :meth:`state_observations` (docs/adding_a_task.md). The base
    gives the observations' common part, the sparse and normalised rewards and the helpers below.

    Shared keyword arguments: ``robot_init_qpos_noise`` (uniform joint noise around the ``rest`` keyframe,
    rad), ``object_shape`` ("cube", "cylinder" or "random": per env, drawn when the scene is built),
    ``object_half_size`` (cube half side, cylinder radius and half height, 3..12 mm), ``object_mass`` (kg),
    ``object_friction``, ``spawn_margin`` (object centre to the source tray's inner walls, m), ``randomization``
    (domain randomisation, off by default: a ``Randomization``, a dict or a spec string; envs/randomization.py).

    ``enhanced_determinism`` defaults to True (ManiSkill's default is False) so that an unseeded ``reset()``
    after ``reset(seed=s)`` draws its episode seed from the seeded main RNG: the gymnasium contract (and its
    env checker) expects that sequence to be reproducible.
    """

    SUPPORTED_ROBOTS = ["irb120_metalwork"]
    SUPPORTED_REWARD_MODES = REWARD_MODES
    agent: IRB120Metalwork
    render_ahead: bool = True
    _captured_ahead: bool = False

    def __init__(
        self,
        *args,
        robot_uids: str = "irb120_metalwork",
        obs_mode: str = "rgbd",
        reward_mode: str | None = None,
        control_mode: str | None = None,
        robot_init_qpos_noise: float = 0.0,
        object_shape: str = "cube",
        object_half_size: float = 0.01,
        object_mass: float = 0.02,
        object_friction: float = 1.0,
        spawn_margin: float = SPAWN_MARGIN,
        randomization=None,
        enhanced_determinism: bool = True,
        **kwargs,
    ):
        if robot_uids not in self.SUPPORTED_ROBOTS:
            raise ValueError(f"robot_uids={robot_uids!r} is not supported; use one of {self.SUPPORTED_ROBOTS}")
        if reward_mode is not None and reward_mode not in self.SUPPORTED_REWARD_MODES:
            raise UsageError(f"reward_mode={reward_mode!r} is not supported; use one of {self.SUPPORTED_REWARD_MODES}")
        self._check_obs_mode(obs_mode)
        self._check_batching(kwargs.get("num_envs", args[0] if args else 1), kwargs.get("sim_backend", "auto"))
        check_object_params(object_shape, object_half_size, object_mass, object_friction)
        if not 0 <= spawn_margin < TRAY_INNER / 2:
            raise ValueError(f"spawn_margin={spawn_margin} must be in [0, {TRAY_INNER / 2})")
        self.robot_init_qpos_noise = robot_init_qpos_noise
        self.object_shape = object_shape
        self.object_half_size = self._nominal_half_size = object_half_size
        self.object_mass = object_mass
        self.object_friction = object_friction
        self.spawn_margin = spawn_margin
        self._init_randomization(randomization)
        if self.randomization.build_ranges() and "reconfiguration_freq" not in kwargs:
            kwargs["reconfiguration_freq"] = 1  # a new draw each episode (envs/randomization.py says why)
        super().__init__(
            *args,
            robot_uids=robot_uids,
            obs_mode=obs_mode,
            reward_mode=reward_mode,
            control_mode=control_mode,
            enhanced_determinism=enhanced_determinism,
            **kwargs,
        )

    # ------------------------------------------------------------------ cameras
    @property
    def _default_sensor_configs(self):
        """No scene cameras: the policy sees only the agent's 84x84 hand camera, as in the original report.
        Every extra sensor would be rendered each step (and concatenated by ManiSkill's RGB-D flattening)."""
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
                raise UsageError(f"control_mode={self._control_mode!r} is not supported: {e}") from None
            raise

    def _object_shapes(self) -> list[str]:
        """Each env's object shape; "random" draws it per env from the episode RNG at scene build."""
        if self.object_shape != "random":
            return [self.object_shape] * self.num_envs
        rngs = self._batched_episode_rng
        return [
            ("cube", "cylinder")[int((rngs[i] if rngs is not None else np.random).randint(2))]
            for i in range(self.num_envs)
        ]

    def _build_object(self, name: str, color) -> Actor:
        obj = build_object(
            self.scene,
            name,
            self._object_shapes(),
            self.object_half_size,
            self.object_mass,
            self.object_friction,
            color,
            own_materials=self.own_materials,
        )
        self._randomize_bodies(obj, self.object_mass, self.object_friction)
        return obj

    def build_trays(self) -> None:
        """First in draw order: the two trays (then the task's objects, :meth:`build_background` and
        :meth:`watch_contacts`). Draws the scene-build randomisation of the object size, so build the objects
        after this."""
        self.table_scene = TableScene(self.scene, self.own_materials)
        self.table_scene.build_trays()
        self.source_tray, self.dest_tray = self.table_scene.source_tray, self.table_scene.dest_tray
        self.object_half_size = self._randomized_build(self._nominal_half_size)
        with torch.device(self.device):
            self.source_center = torch.tensor([*SOURCE_TRAY_XY, TRAY_FLOOR_TOP]).repeat(self.num_envs, 1)
            self._fresh = torch.ones(self.num_envs, dtype=torch.bool)
        # host-side: no env is fresh (known without reading _fresh, which on the GPU would wait for it); then
        # the last step's values need no select against this step's (_last)
        self._none_fresh = False
        self._cur: dict[str, torch.Tensor] = {}
        self._prev: dict[str, torch.Tensor] = {}

    def build_background(self) -> None:
        """Table and floor, after the objects: built last, they are drawn last, so most of their pixels fail
        the CPU rasteriser's early depth test (envs/scene.py)."""
        self.table_scene.build_background()
        self.scene_actors = self.table_scene.actors

    def watch_contacts(self, objects: list[Actor]) -> None:
        """``self.contacts`` watches the robot against the scene, ``objects`` against the scene and the fingers
        against ``objects`` (in this order: ``object_hit[j]`` and ``finger_forces[j]`` are ``objects[j]``'s);
        the domain randomisation's colour jitter applies to them too."""
        self._dr_objects = objects
        self.fingers = [self.agent.finger_left, self.agent.finger_right]
        robot_links = [link for link in self.agent.robot.links if link.name != "base_link"]
        self.contacts = Contacts(self.scene, robot_links, self.fingers, self.scene_actors, objects)

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: int | list[int] | None = None, options: dict | None = None):
        """ManiSkill's reset, plus gymnasium's ``np_random`` seeded alike (ManiSkill keeps its own RNGs and
        never seeds it), and the mask of the envs being reset kept for the controllers (maniskill_compat)."""
        self._check_open()
        options = self._checked_reset_options(options)
        if seed is not None:
            first = int(seed[0]) if np.iterable(seed) else int(seed)
            self._np_random, self._np_random_seed = gym_seeding.np_random(first)
        if self.scene is None:  # first reset: the scene (and every env in it) is built anew
            return super().reset(seed=seed, options=options)
        with episode_reset(self.scene, reset_mask_from_options(self.num_envs, options, self.device)):
            return super().reset(seed=seed, options=options)

    def _episode_draws(self, env_idx: torch.Tensor, **sizes: int) -> dict[str, torch.Tensor]:
        """Uniform [0, 1) draws per env being reset, from ManiSkill's per-env episode RNG: a GPU env with
        episode seed s starts where a CPU env reset with seed s does. (On the GPU ManiSkill seeds torch with env
        0's episode seed before every reset, so torch draws would repeat one start in every partial reset that
        leaves env 0 running.)

        Named: ``_episode_draws(env_idx, joint_noise=6, obj_xy=2, obj_yaw=1)`` returns a dict of ``(b, size)``
        tensors, drawn in the order named (one stream per env: reordering or resizing a name changes every
        later draw, and so every seed's start)."""
        if not sizes:
            raise TypeError("_episode_draws needs named sizes, e.g. joint_noise=6")
        total = sum(sizes.values())
        rng = self._batched_episode_rng[env_idx.cpu().numpy()]
        u = torch.as_tensor(rng.uniform(size=total), dtype=torch.float32, device=self.device).reshape(-1, total)
        return dict(zip(sizes, torch.split(u, list(sizes.values()), dim=1)))

    def _reset_robot(self, env_idx: torch.Tensor, u: torch.Tensor) -> None:
        """The ``rest`` keyframe plus ``robot_init_qpos_noise`` · (2u - 1) on the arm joints; u: (b, 6) draws."""
        qpos = torch.as_tensor(self.agent.keyframes["rest"].qpos, dtype=torch.float32, device=self.device)
        qpos = qpos.repeat(len(env_idx), 1)
        if self.robot_init_qpos_noise > 0:
            qpos[:, :6] += (u * 2 - 1) * self.robot_init_qpos_noise
        self.agent.reset(qpos)
        self.agent.set_step_start(env_idx, qpos)
        self.agent.robot.set_pose(sapien.Pose())
        self.agent.invalid_action[env_idx] = False
        self._fresh[env_idx] = True
        self._none_fresh = False
        self._captured_ahead = False  # a reset's observation is always captured afresh
        self._randomize_episode(env_idx)

    def _spawn_in_source_tray(self, xy: torch.Tensor, yaw: torch.Tensor) -> Pose:
        """Resting poses in the source tray's inner square shrunk by ``spawn_margin``, uniform yaw; ``xy``:
        (b, 2) and ``yaw``: (b, 1) draws in [0, 1). Spawned resting rather than dropped: ``_initialize_episode``
        cannot step physics, and a falling object at t = 0 would make the first rewards depend on the settling
        transient."""
        span = TRAY_INNER / 2 - self.spawn_margin
        b = xy.shape[0]
        xyz = torch.full((b, 3), TRAY_FLOOR_TOP + self.object_half_size, device=self.device)
        xyz[:, :2] = (xy * 2 - 1) * span + torch.tensor(SOURCE_TRAY_XY, device=self.device)
        return Pose.create_from_pq(xyz, yaw_quat(yaw[:, 0] * 2 * math.pi))

    def _before_control_step(self):
        """The state evaluated after the last step (or reset) becomes the reference for this step."""
        self._prev = {k: v.clone() for k, v in self._cur.items()}
        self._fresh[:] = False
        self._none_fresh = True
        self.contacts.stepped()

    def _last(self, key: str, now: torch.Tensor) -> torch.Tensor:
        """The last step's value of ``key`` (``now`` itself right after a reset)."""
        if self._none_fresh and key in self._prev:
            return self._prev[key]
        return torch.where(self._fresh.view(-1, *[1] * (now.dim() - 1)), now, self._prev.get(key, now))

    def _previous(self, cur: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Record ``cur`` as this step's state and return the last step's (``cur`` itself right after a
        reset): edge-triggered events compare the two. Idempotent between steps."""
        prev = {k: self._last(k, v) for k, v in cur.items()}
        self._cur = cur
        return prev

    def _speed(self, key: str, pos: torch.Tensor) -> torch.Tensor:
        """(N,) speed over the last control step from positions (N, 3) recorded under ``key`` (include it in
        ``_previous``). PhysX's body velocity of an object squeezed in the gripper is not usable: it reads a
        steady few cm/s and rad/s while the object does not move."""
        return torch.linalg.norm(pos - self._last(key, pos), dim=1) * self.control_freq

    # ------------------------------------------------------------------ contacts and grasps
    def _grasped(self, finger_forces: torch.Tensor, tcp_quat: torch.Tensor, closed: bool = True) -> torch.Tensor:
        """(N,) both fingers squeeze the object whose (2, N, 3) finger forces these are and, with ``closed``, the
        gripper is commanded closed. The open fingers leave 26 mm, less than a 20 mm cube's diagonal: pushed down
        on a cube yawed 23-45 degrees off them, they wedge it and push on it along their closing direction too, and
        SAC from the reward alone learned to collect the grasp stage's pay that way, never closing the gripper
        (docs/notes/rl-from-the-reward.md)."""
        squeeze = self.agent.is_grasping(None, finger_forces=finger_forces, tcp_quat=tcp_quat)
        return squeeze & self.agent.gripper_commanded_closed if closed else squeeze

    def _common_info(self, robot_hit: torch.Tensor, grasped: torch.Tensor) -> dict[str, torch.Tensor]:
        """The ``info`` entries every task reports: a collision ends the episode as a failure."""
        return dict(
            fail=robot_hit,
            collided=robot_hit,
            grasped=grasped,
            is_grasped=grasped,
            ik_unreachable=self.agent.ik_unreachable.clone(),
            invalid_action=self.agent.invalid_action.clone(),
        )

    @staticmethod
    def _touches(finger_forces: torch.Tensor) -> torch.Tensor:
        """(N,) either finger touches the object whose (2, N, 3) finger forces these are."""
        return (torch.linalg.norm(finger_forces, dim=2) > CONTACT_FORCE_EPS).any(0)

    # ------------------------------------------------------------------ what other layers may read
    # The experts, the auxiliary losses and the real side (sim2real/env.py) read a task only through these, so a
    # task may name its own attributes as it likes: on the real side a private name is an error, not the sim's.

    target_object: Actor
    """The object the expert picks and auxiliary losses look at (set in ``_load_scene``)."""

    MAX_STAGED_REWARD = 4.0
    """The staged dense reward's value on success: ``normalized_dense`` = staged reward / this. The staged
    rewards are banded: stage k (0 = reach) pays k + progress with progress in [0, 1), so each stage's
    maximum is below the next stage's minimum and ``floor(dense)`` is the stage; success pays 4 (1 normalised),
    more per step than any other state. Success ends the episode: as in ManiSkill, a learner should treat it
    as an absorbing state of reward 1 per step (bootstrap the value at success, as ``agents/ppo.py`` does, or
    ``ignore_terminations``); returns cut at success favour stalling in a late stage."""

    step_state: dict[str, torch.Tensor]
    """This step's poses, read once in ``evaluate`` (:meth:`_read_step_state`): :meth:`privileged_state`'s
    entries plus ``"tcp_pose"`` (and, under tuple keys, values derived from them once a step, such as
    :func:`step_grasp_yaw_error`'s). Observations and rewards read poses only from here; on the real side
    ``IRB120Sim2RealEnv`` fills it from the robot's FK and the digital twin's :meth:`privileged_state`."""

    def privileged_state(self) -> dict[str, torch.Tensor]:
        """The object poses the task's observations read, ``(N, 7)`` raw poses (position, wxyz quaternion) keyed
        by names the task chooses: what a perception system (or the emulator's digital twin) must supply for
        state observations on the real side. Read live from the sim."""
        raise NotImplementedError(f"{type(self).__name__} must say which object poses it observes")

    @property
    def tcp_pose(self) -> torch.Tensor:
        """(N, 7) raw TCP pose of this step (the one the observations and rewards use)."""
        return self.step_state["tcp_pose"]

    def _read_step_state(self) -> dict[str, torch.Tensor]:
        """Fetch this step's poses once (call first in ``evaluate``): observations and rewards of a step then
        read the same values."""
        state = self.privileged_state()
        if "tcp_pose" in state:
            raise ValueError(f"{type(self).__name__}.privileged_state() must not use the name 'tcp_pose'")
        self.step_state = {**state, "tcp_pose": raw_pose(self.agent.tcp)}
        return self.step_state

    def _get_obs_extra(self, info: dict) -> dict[str, torch.Tensor]:
        """The TCP pose and the grasp flag, plus :meth:`state_observations` in state obs modes. Copies: writing
        into an observation must not move what the env scores against. Reads only ``self.step_state``,
        ``info`` and public attributes, so the real side runs it as it is (``self``: the real env)."""
        state = self.step_state
        obs = dict(tcp_pose=state["tcp_pose"].clone(), is_grasped=info["grasped"].clone())
        if self.obs_mode_struct.use_state:
            obs.update(self.state_observations(state, info))
        return obs

    def state_observations(self, state: dict[str, torch.Tensor], info: dict) -> dict[str, torch.Tensor]:
        """The task's privileged observations (state obs modes), computed from ``state`` (a step state), ``info``
        and the task's fixed geometry only: on the real side ``state`` is the one built from the robot and the
        world, and ``self`` is the sim."""
        return {}

    def compute_sparse_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """1 on success, else 0."""
        return info["success"].float()

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        """The staged dense reward over :attr:`MAX_STAGED_REWARD`, in [0, 1]."""
        return self.compute_dense_reward(obs, action, info) / self.MAX_STAGED_REWARD

    # ------------------------------------------------------------------ render-ahead (CPU)
    def _after_control_step(self):
        """Start this step's camera frame now, before ``evaluate``: on the CPU the rasteriser draws it in its
        own threads while this thread evaluates the step, and ``get_obs`` then only reads it back (the gain is in
        docs/notes/sim-speed.md). The scene does not change in between, so the images are the
        ones ManiSkill's capture in ``get_obs`` takes (tested). GPU sim: ManiSkill's path."""
        if (
            not self.render_ahead
            or self.gpu_sim_enabled
            or not self._sensors
            or self._obs_mode in ("state", "state_dict", "none")
        ):
            return
        for obj in self._hidden_objects:
            obj.hide_visual()
        self.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        self.capture_sensor_data()
        self._captured_ahead = True

    def _get_obs_sensor_data(self, apply_texture_transforms: bool = True) -> dict:
        if not self._captured_ahead:
            return self._randomize_sensor_data(super()._get_obs_sensor_data(apply_texture_transforms))
        self._captured_ahead = False
        return self._randomize_sensor_data(read_sensor_obs(self, apply_texture_transforms))

    # ------------------------------------------------------------------ state
    EPISODE_STATE: tuple[str, ...] = ()
    """Names of (N, ...) task attributes drawn or recorded per episode that ``evaluate`` reads (e.g. where the
    object started): they travel in the env state's ``memory``."""

    def get_state_dict(self) -> dict:
        """ManiSkill's (actors, articulations, the controllers), plus ``memory``: what the next observation and
        ``info`` depend on beyond the physics, so that ``set_state_dict`` then ``get_obs`` gives the observation
        taken at this state. All (N, D) float32 rows: the agent's (``step_start_qpos``: the observation's ``qvel`` is
        the step's displacement; ``gripper_target``: its last command), ``fresh`` (just reset: edge-triggered events
        and speeds see no last step), ``contact_*`` (the contacts this state was evaluated with: a restore moves the
        bodies, not PhysX's contact list),
        ``prev_*`` and ``cur_*`` (the edge-triggered events' last and this step's values) and :attr:`EPISODE_STATE`."""
        state = super().get_state_dict()
        if not self._cur:  # evaluated at every reset and step; only a state read before any has none
            self.evaluate()
        n = self.num_envs
        memory = dict(**self.agent.get_memory(), fresh=self._fresh.float()[:, None])
        memory.update({f"contact_{k}": v for k, v in self.contacts.state().items()})
        for k, v in self._cur.items():
            memory[f"prev_{k}"] = self._prev.get(k, v).reshape(n, -1).float()
            memory[f"cur_{k}"] = v.reshape(n, -1).float()
        memory.update({k: getattr(self, k).reshape(n, -1).float() for k in self.EPISODE_STATE})
        state["memory"] = memory
        return state

    def set_state_dict(self, state: dict, env_idx: torch.Tensor | None = None):
        """ManiSkill's, plus the controller state it records but does not restore, plus :meth:`get_state_dict`'s
        memory. A state recorded without memory (before it existed) restores as after a reset: ``qvel`` zero,
        no last step, PhysX's contacts."""
        super().set_state_dict(state, env_idx)
        restore_controller_state(self, state, env_idx)
        self._restore_memory(state.get("memory"), env_idx)

    def set_state(self, state, env_idx: torch.Tensor | None = None):
        """ManiSkill's (which goes through ``set_state_dict`` without the controller and memory parts), plus
        those parts from the flat vector's tail."""
        super().set_state(state, env_idx)
        restore_controller_state(self, state, env_idx)
        memory = state_extras(self, state).get("memory")
        if memory is not None:
            self._restore_memory(memory, env_idx)

    def _restore_memory(self, memory: dict | None, env_idx: torch.Tensor | None) -> None:
        """Rows ``env_idx`` (all when None) of :meth:`get_state_dict`'s memory; None: as after a reset."""
        self._captured_ahead = False  # a frame rendered ahead shows the state before the restore
        n = self.num_envs
        rows = torch.arange(n, device=self.device) if env_idx is None else torch.as_tensor(env_idx, device=self.device)
        rows = rows.long()
        if memory is None:
            self.agent.set_memory(rows, None)
            self._fresh[rows] = True
            self._none_fresh = False
            self.contacts.stepped()
            return
        # (D,) rows too: ManiSkill's CPU replay restores one env's unbatched state
        memory = {k: torch.as_tensor(v, device=self.device).reshape(len(rows), -1) for k, v in memory.items()}
        self.agent.set_memory(rows, memory)
        self._fresh[rows] = memory["fresh"][:, 0] > 0.5
        self._none_fresh = False
        self.contacts.restore({k: memory[f"contact_{k}"] for k in ("robot_hit", "object_hit", "finger_forces")}, rows)
        if not self._cur:
            self.evaluate()
        for k, cur in list(self._cur.items()):
            self._prev[k] = _set_rows(self._prev.get(k, cur), rows, memory[f"prev_{k}"])
            self._cur[k] = _set_rows(cur, rows, memory[f"cur_{k}"])
        for k in self.EPISODE_STATE:
            setattr(self, k, _set_rows(getattr(self, k), rows, memory[k]))


def _set_rows(current: torch.Tensor, rows: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """A copy of ``current`` with ``rows`` set from (len(rows), D) float ``values`` in its own dtype and shape."""
    out = current.clone()
    out[rows] = values.reshape(len(rows), *current.shape[1:]).to(current.dtype)
    return out


def reach_reward(dist: torch.Tensor) -> torch.Tensor:
    """(N,) reach term of the staged rewards, 1 - tanh(REACH_SCALE · dist), in (0, 1] (dist: (N,) metres)."""
    return 1 - torch.tanh(REACH_SCALE * dist)


def grasp_approach_reward(
    obj_pose: torch.Tensor, tcp_pose: torch.Tensor, yaw_error: torch.Tensor | None = None
) -> torch.Tensor:
    """(N,) the staged rewards' reach stage for a side grasp, in [0, 1): what ManiSkill's ``1 - tanh(5·d)``
    is for the Panda, at the precision our gripper needs.

    The open MetalWork fingers leave 3 mm either side of a 20 mm cube (the Panda: 20 mm), so the grasp needs
    the TCP within a few millimetres of the object's axis and the finger axis turned onto a face; a plain
    distance term is flat there (3 mm off costs 0.002 of ``normalized_dense``), and from scratch PPO learned
    to approach, never to grasp. The term is the mean of four parts, each rising along the expert's path:
    twice the coarse reach ``1 - tanh(3·d)`` to the grasp point (``GRASP_POINT_OFFSET`` above the centre);
    the alignment ``(1 - tanh(40·horizontal distance)) · (1 - |yaw error| / 45°)``, which resolves
    millimetres and degrees; and the alignment times ``1 - tanh(40·|height error|)``, so descending pays only
    once aligned (descending beside the object hits it or the tray). ``obj_pose``/``tcp_pose``: (N, 7) raw;
    ``yaw_error``: their :func:`grasp_yaw_error` when the caller has it (:func:`step_grasp_yaw_error`)."""
    if yaw_error is None:
        yaw_error = grasp_yaw_error(obj_pose, tcp_pose)
    grasp_point = obj_pose[:, :3] + up(GRASP_POINT_OFFSET, obj_pose)
    return aligned_reach_reward(grasp_point - tcp_pose[:, :3], 1 - yaw_error.abs() / (math.pi / 4))


_UP: dict[tuple, torch.Tensor] = {}


def up(height: float, like: torch.Tensor) -> torch.Tensor:
    """(3,) the offset ``height`` straight up, as ``like``'s dtype and device, made once: adding it to positions is
    one op where a copy and an in-place add to its z are three, for the same numbers."""
    key = (height, like.dtype, like.device)
    if key not in _UP:
        if len(_UP) > 64:  # a size drawn anew at each build (domain randomisation) would otherwise pile up
            _UP.clear()
        _UP[key] = torch.tensor([0.0, 0.0, height], dtype=like.dtype, device=like.device)
    return _UP[key]


def aligned_reach_reward(offset: torch.Tensor, align_factor: torch.Tensor | None = None) -> torch.Tensor:
    """(N,) in [0, 1): getting to a point that needs millimetres (``offset``: (N, 3) from here to it), as the mean
    of twice the coarse reach ``1 - tanh(3·d)``, the horizontal alignment ``1 - tanh(40·horizontal distance)``
    (times ``align_factor``, e.g. the grasp's yaw term), and the alignment times ``1 - tanh(40·|height error|)``:
    descending pays only once aligned above the point. :func:`grasp_approach_reward` reaches the grasp with it,
    StackCube's place stage the top of the other cube; a plain ``1 - tanh(3·d)`` is flat there (3 mm: 0.002)."""
    coarse = reach_reward(torch.linalg.norm(offset, dim=1))
    align = 1 - torch.tanh(ALIGN_SCALE * torch.linalg.norm(offset[:, :2], dim=1))
    if align_factor is not None:
        align = align * align_factor
    down = 1 - torch.tanh(ALIGN_SCALE * offset[:, 2].abs())
    return ((2 * coarse + align + align * down) / 4).clamp(max=0.999)


def step_grasp_yaw_error(state: dict[str, torch.Tensor], key: str) -> torch.Tensor:
    """(N,) :func:`grasp_yaw_error` of ``state[key]`` and ``state["tcp_pose"]`` for a step state
    (``IRB120TableEnv.step_state``), computed once per step state: a state observation and the reach reward both
    read it, on the sim and on the real side (each builds a new step state every step). Kept in ``state`` under
    ``("grasp_yaw_error", key)``; a copy is returned, so writing into an observation cannot move the reward."""
    cached = ("grasp_yaw_error", key)
    if cached not in state:
        state[cached] = grasp_yaw_error(state[key], state["tcp_pose"])
    return state[cached].clone()


def yaw_quat(yaw: torch.Tensor) -> torch.Tensor:
    """(b, 4) wxyz quaternions of rotations by ``yaw`` about world z."""
    return torch.stack([torch.cos(yaw / 2), 0 * yaw, 0 * yaw, torch.sin(yaw / 2)], 1)


def _quadratic_map(entries: dict[tuple[int, int], dict[str, float]]) -> torch.Tensor:
    """(16, K) map from a quaternion's outer product (w, x, y, z; flattened) to K rotation-matrix entries, each
    given as ``{(row, col): {"wx": coefficient, ...}}``: unnormalised (the entries of R times |q|²)."""
    index = {c: i for i, c in enumerate("wxyz")}
    m = torch.zeros(16, len(entries))
    for k, terms in enumerate(entries.values()):
        for pair, coef in terms.items():
            i, j = index[pair[0]], index[pair[1]]
            m[4 * i + j, k] += coef / 2 if i != j else coef
            if i != j:
                m[4 * j + i, k] += coef / 2
    return m


# R in terms of q = (w, x, y, z), times |q|²: diagonal w² ± ..., off-diagonal 2(ab ± cd)
_R = {
    (0, 0): dict(ww=1, xx=1, yy=-1, zz=-1), (1, 0): dict(xy=2, wz=2), (2, 0): dict(xz=2, wy=-2),
    (0, 1): dict(xy=2, wz=-2), (1, 1): dict(ww=1, xx=-1, yy=1, zz=-1), (2, 1): dict(yz=2, wx=2),
    (0, 2): dict(xz=2, wy=2), (1, 2): dict(yz=2, wx=-2), (2, 2): dict(ww=1, xx=-1, yy=-1, zz=1),
}  # fmt: skip
# the object: its third row (which axis is most horizontal), then each column's x and y; the TCP: column 1's x, y
_OBJ_MAP = _quadratic_map({k: _R[k] for k in [(2, 0), (2, 1), (2, 2), (0, 0), (1, 0), (0, 1), (1, 1), (0, 2), (1, 2)]})
_TCP_MAP = _quadratic_map({k: _R[k] for k in [(0, 1), (1, 1)]})
_MAPS: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}


def grasp_yaw_error(obj_pose: torch.Tensor, tcp_pose: torch.Tensor) -> torch.Tensor:
    """(N,) rotation about world z (radians, in [-π/4, π/4)) that turns the finger axis onto the nearest side
    face normal of a cube-like object (its 90° symmetry) — the smallest turn before a side grasp.

    A state observation: from two raw quaternions this angle is a function of four times the object's yaw
    (period 90°), which an MLP policy barely learns; given directly, the grasp alignment is one input.
    ``obj_pose``/``tcp_pose``: (N, 7) raw poses (position, wxyz quaternion).

    It runs two or three times a step (observation, reward, expert), so it reads the eleven matrix entries it
    needs as one product of each quaternion's outer product with a constant map instead of building two full
    rotation matrices; the |q|² they all carry cancels in the argmin and the atan2s."""
    key = (obj_pose.device, obj_pose.dtype)
    if key not in _MAPS:
        _MAPS[key] = (_OBJ_MAP.to(obj_pose), _TCP_MAP.to(obj_pose))
    obj_map, tcp_map = _MAPS[key]
    q, t = obj_pose[:, 3:], tcp_pose[:, 3:]
    obj = (q[:, :, None] * q[:, None, :]).reshape(-1, 16) @ obj_map  # (N, 9)
    fingers = (t[:, :, None] * t[:, None, :]).reshape(-1, 16) @ tcp_map  # (N, 2): the finger axis' x, y
    # the object's most horizontal axis is a side-face normal (any resting pose of a cube)
    axis_idx = obj[:, :3].abs().argmin(dim=1)
    normal = torch.gather(obj[:, 3:].reshape(-1, 3, 2), 1, axis_idx.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
    delta = torch.atan2(normal[:, 1], normal[:, 0]) - torch.atan2(fingers[:, 1], fingers[:, 0])
    return torch.remainder(delta + math.pi / 4, math.pi / 2) - math.pi / 4
