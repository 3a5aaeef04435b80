"""The envs trainers collect from and the observations they read: every trainer's vector envs (:func:`vec_envs`),
batched torch obs as a dict, devices, the policy's action-frame wrappers, and the labelled vector envs of the
imitation and demo-seeded trainers (:func:`make_envs`). See docs/training.md."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Optional

import gymnasium as gym
import torch
from mani_skill.utils import common as ms_common

from maniskill_irb120.action import tcp_rotation, tool_to_world, world_to_tool
from maniskill_irb120.envs.base import grasp_yaw_error
from maniskill_irb120.experts import expert_for
from maniskill_irb120.policies import acting, read_policy_section
from maniskill_irb120.vector import CPUVectorEnv, OnHost, make_vec_env
from maniskill_irb120.wrappers import WorldFrameToolAction, observation_setup


def flatten_obs(obs) -> dict[str, torch.Tensor]:
    """Normalise both obs layouts to a dict with 'state' (and 'rgb'/'depth' for rgbd)."""
    if isinstance(obs, torch.Tensor):
        return {"state": obs}
    return obs


def obs_to(obs: dict, device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in obs.items()}


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


AUX_DIM = 5
MOUNT_AUX_DIM = 6
"""with ``mount``: the camera's offset from its nominal mount, 3 positions and 3 angles"""


def aux_dim(mount: bool = False) -> int:
    """How many targets :func:`privileged_aux` gives, with or without the mount."""
    return AUX_DIM + (MOUNT_AUX_DIM if mount else 0)


def privileged_aux(env: gym.Env, frame: str = "world", mount: bool = False) -> torch.Tensor:
    """(N, 5) what a camera policy has to find in its image: the object's position relative to the TCP (in the
    learner's action frame: world or tool axes; in decimetres, so about unit scale) and the grasp yaw error as
    sin/cos of four times it (continuous across the cube's 90° symmetry). With ``mount``, (N, 11): then the hand
    camera's offset from its nominal mount, as the randomisation drew it (``camera_pos`` in cm, ``camera_rot`` in
    units of 5°; zero where the env draws no mount). The object's place relative to the TCP reads the same under
    any mount, so a student can fit it by assuming the nominal one; the mount itself can only be read off the
    frame, from where the gripper's fingers appear in it."""
    u = env.unwrapped
    if mount:
        return torch.cat([privileged_aux(env, frame), mount_offset(env)], dim=1)
    obj, tcp = u.target_object.pose.raw_pose, u.tcp_pose  # the task's declared interface (envs/base.py)
    rel = (obj[:, :3] - tcp[:, :3]) * 10.0
    if frame == "tool":  # the hand camera's own axes: an offset in the image is one in the tool frame
        rel = (tcp_rotation(tcp).transpose(1, 2) @ rel.unsqueeze(2)).squeeze(2)
    yaw = 4.0 * grasp_yaw_error(obj, tcp)
    return torch.cat([rel, yaw.sin()[:, None], yaw.cos()[:, None]], dim=1).float()


def mount_offset(env: gym.Env) -> torch.Tensor:
    """(N, 6) the hand camera's drawn offset from its nominal mount: position in cm, rotation in units of 5°."""
    u = env.unwrapped
    draws = getattr(u, "randomization_draws", {})
    out = torch.zeros(u.num_envs, MOUNT_AUX_DIM)
    if "camera_pos" in draws:
        out[:, :3] = draws["camera_pos"].float() * 100.0
    if "camera_rot" in draws:
        out[:, 3:] = draws["camera_rot"].float() / 5.0
    return out.to(u.device)


def privileged_state_obs(env: gym.Env, info: dict) -> torch.Tensor:
    """(N, D) the observation ``obs_mode="state"`` gives at this step, whatever the env's own obs mode: the agent's
    proprioception and the task's extras with its privileged :meth:`state_observations`, flattened in ManiSkill's
    order. What a state teacher reads while its camera student reads the image (teacher–student)."""
    u = env.unwrapped
    extra = u._get_obs_extra(info)
    if not u.obs_mode_struct.use_state:
        extra.update(u.state_observations(u.step_state, info))
    return ms_common.flatten_state_dict(dict(agent=u._get_obs_agent(), extra=extra), use_torch=True, device=u.device)


PRIVILEGED = "privileged"
"""the observation key :class:`PrivilegedStateObs` adds"""


class PrivilegedStateObs(gym.Wrapper):
    """Adds ``privileged``, the (N, D) :func:`privileged_state_obs` of the state just reached, to a dict observation
    (the flattened camera one: rgb/depth/state) and to its observation space, at every reset and step. Training
    only: what an asymmetric critic reads (agents.ppo ``--critic-obs privileged``); being part of the observation, it
    travels as the camera does, through the CPU workers' shared memory, an auto-reset's ``final_observation`` and a
    rollout's storage, while the policy reads only its own keys."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        u = env.unwrapped
        init = u._init_raw_obs  # the flattened observation the wrapper inside set its space from
        if not isinstance(init, dict) or PRIVILEGED in init:
            raise ValueError(
                f"PrivilegedStateObs adds {PRIVILEGED!r} to a dict observation without it; got {type(init)}"
            )
        u.update_obs_space(dict(init, **{PRIVILEGED: privileged_state_obs(env, u.get_info())}))

    def _add(self, obs: dict, info: dict) -> dict:
        if "grasped" not in info:  # a reset's info carries no evaluation
            info = {**self.env.unwrapped.get_info(), **info}
        return dict(obs, **{PRIVILEGED: privileged_state_obs(self.env, info)})

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return self._add(obs, info), info

    def step(self, action):
        obs, rew, term, trunc, info = self.env.step(action)
        return self._add(obs, info), rew, term, trunc, info


class ActionLabels(gym.Wrapper):
    """Puts a labeller's action for the state just reached into ``info["expert_action"]``, in the learner's action
    frame (``world``: its translation rotated out of the tool frame), and with ``aux`` the auxiliary targets
    (:func:`privileged_aux`) into ``info["expert_aux"]``. Subclasses say where the tool-frame action comes from."""

    def __init__(self, env: gym.Env, frame: str = "tool", aux: bool = False, aux_mount: bool = False):
        super().__init__(env)
        if aux_mount and not aux:
            raise ValueError("the mount is an auxiliary target: --aux-mount needs --aux-weight > 0")
        if frame not in ("tool", "world"):
            raise ValueError(f"unknown action frame {frame!r}; expected 'tool' or 'world'")
        if aux and getattr(env.unwrapped, "target_object", None) is None:
            raise ValueError(
                f"--aux-weight needs a task that declares a target_object; {env.unwrapped.spec.id} does not"
            )
        self.frame, self.aux, self.aux_mount = frame, aux, aux_mount

    def tool_action(self, info: dict) -> torch.Tensor:
        """(N, 5) the label in the tool frame, for the state just reached (``info``: its step's or reset's)."""
        raise NotImplementedError

    def _label(self, info: dict) -> None:
        a = self.tool_action(info)
        info["expert_action"] = (
            tool_to_world(a, tcp_rotation(self.env.unwrapped.agent.tcp_pose.raw_pose)) if self.frame == "world" else a
        )
        if self.aux:
            info["expert_aux"] = privileged_aux(self.env, self.frame, self.aux_mount)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._label(info)
        return obs, info

    def step(self, action):
        obs, rew, term, trunc, info = self.env.step(action)
        self._label(info)
        return obs, rew, term, trunc, info


class ExpertLabels(ActionLabels):
    """Labels from the task's reactive scripted expert (its phase read from the simulator)."""

    def __init__(self, env: gym.Env, frame: str = "tool", aux: bool = False, aux_mount: bool = False):
        super().__init__(env, frame, aux, aux_mount)
        self.expert = expert_for(env, reactive=True)

    def tool_action(self, info: dict) -> torch.Tensor:
        return self.expert.act()

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.expert.reset((kwargs.get("options") or {}).get("env_idx"))  # a batched env resets ended envs only
        self._label(info)
        return obs, info


class TeacherLabels(ActionLabels):
    """Labels from a trained state policy (teacher–student): the teacher acts, deterministically, on the privileged
    state observation (:func:`privileged_state_obs`) while the learner reads its own observation, e.g. the camera.
    With a teacher that learned from the reward alone, nothing in the pipeline is scripted or demonstrated."""

    def __init__(self, env: gym.Env, teacher: Path, frame: str = "tool", aux: bool = False, aux_mount: bool = False):
        super().__init__(env, frame, aux, aux_mount)
        self.section = check_teacher(read_policy_section(teacher, f"--teacher {teacher}"), env, teacher)
        self.act = acting(self.section, device=env.unwrapped.device)

    def tool_action(self, info: dict) -> torch.Tensor:
        if "grasped" not in info:  # a reset's info carries no evaluation
            info = {**self.env.unwrapped.get_info(), **info}
        with torch.no_grad():
            a = self.act({"state": privileged_state_obs(self.env, info)}).clamp(-1, 1)
        if self.section["action_frame"] == "world":
            a = world_to_tool(a, tcp_rotation(self.env.unwrapped.agent.tcp_pose.raw_pose))
        return a.float()


def check_teacher(section: dict, env: gym.Env, path) -> dict:
    """``section``, once it is a policy that can label ``env``: one trained from state on this task and control mode,
    seeing every state key (a hidden key would need its own observation layout)."""
    where, u = f"--teacher {path}", env.unwrapped
    wanted = dict(obs="state", env_id=u.spec.id.split(":")[-1], control_mode=u.control_mode, obs_without=[])
    have = dict(
        obs=section["obs"],
        env_id=section["env_id"].split(":")[-1],
        control_mode=section["control_mode"],
        obs_without=list(section["obs_without"]),
    )
    differ = [f"{k}={have[k]!r} (needed: {wanted[k]!r})" for k in wanted if have[k] != wanted[k]]
    if differ:
        raise ValueError(f"{where} cannot label this run: " + ", ".join(differ))
    return section


def check_teacher_file(teacher) -> None:
    """A missing or unreadable --teacher is named here, before any worker starts (a worker's error reads worse)."""
    read_policy_section(Path(teacher), f"--teacher {teacher}")


def action_wrappers(frame: str) -> list:
    """The wrappers between a policy in ``frame`` and the tool-frame env (``world``: WorldFrameToolAction)."""
    return [WorldFrameToolAction] if frame == "world" else []


def vec_envs(
    env_id: str,
    obs: str,
    num_envs: int,
    *,
    backend: str = "auto",
    action_frame: str = "world",
    obs_without: tuple[str, ...] = (),
    control_mode: str = "pd_ee_delta_tool",
    env_kwargs: Optional[dict] = None,
    render: bool = False,
    outer_wrappers: Sequence[Callable] = (),
    ignore_terminations: bool = False,
):
    """``num_envs`` envs of the task as a policy on ``obs`` sees and drives them: its observation (the camera's
    image flattened to rgb/depth/state, the ``obs_without`` keys hidden) and its action frame, with
    ``outer_wrappers`` outside those (labels, video), through ``make_vec_env``. Every trainer's envs are made here;
    an env that renders nothing (state obs, no ``render``) skips the renderer (less memory, faster steps)."""
    obs_mode, obs_wrappers = observation_setup(obs, obs_without)
    kwargs = dict(obs_mode=obs_mode, control_mode=control_mode, **(env_kwargs or {}))
    if obs == "rgbd" or render:
        kwargs["render_mode"] = "rgb_array"
    else:
        kwargs.setdefault("render_backend", "none")
    wrappers = [*obs_wrappers, *action_wrappers(action_frame), *outer_wrappers]
    if obs == "rgbd":
        from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

        wrappers.insert(len(obs_wrappers), FlattenRGBDObservationWrapper)  # -> {"rgb", "depth", "state"}
    return make_vec_env(
        env_id,
        num_envs,
        backend=backend,
        wrappers=wrappers,
        ignore_terminations=ignore_terminations,
        record_metrics=True,
        **kwargs,
    )


def make_envs(
    env_id: str,
    obs: str,
    num_envs: int,
    *,
    backend: str = "auto",
    action_frame: str = "world",
    obs_without: tuple[str, ...] = (),
    aux: bool = False,
    env_kwargs: Optional[dict] = None,
    teacher: Optional[Path] = None,
    aux_mount: bool = False,
):
    """``num_envs`` envs whose info carries a label for every state, the reactive expert's (:class:`ExpertLabels`) or
    with ``teacher`` a trained state policy's (:class:`TeacherLabels`), with ``aux`` the auxiliary targets too (with
    ``aux_mount`` the camera's mount among them), in the policy's observation and action frame, as host tensors."""
    if teacher is None:
        labels = partial(ExpertLabels, frame=action_frame, aux=aux, aux_mount=aux_mount)
    else:
        check_teacher_file(teacher)
        labels = partial(TeacherLabels, teacher=Path(teacher), frame=action_frame, aux=aux, aux_mount=aux_mount)
    backend = "inprocess" if backend == "cpu" and num_envs == 1 else backend  # auto: make_vec_env's
    envs = one_thread_beside_workers(
        vec_envs(
            env_id,
            obs,
            num_envs,
            backend=backend,
            action_frame=action_frame,
            obs_without=obs_without,
            env_kwargs=env_kwargs,
            outer_wrappers=[labels],
        )
    )
    # the dataset and the replay live in host memory: a batched env's tensors come back to the CPU each step
    return envs if isinstance(envs, CPUVectorEnv) else OnHost(envs)


def labelled_envs(args, num_envs: int):
    """:func:`make_envs` for a run's arguments: its task, observation (less ``obs_without``), action frame,
    backend and ``env_kwargs``, with its ``reward_mode``, auxiliary targets (``aux_weight`` > 0) and ``teacher``
    where its trainer has those flags."""
    env_kwargs = dict(args.env_kwargs)
    if hasattr(args, "reward_mode"):
        env_kwargs["reward_mode"] = args.reward_mode
    return make_envs(
        args.env_id,
        args.obs,
        num_envs,
        backend=args.backend,
        action_frame=args.action_frame,
        obs_without=args.obs_without,
        aux=getattr(args, "aux_weight", 0) > 0,
        env_kwargs=env_kwargs,
        teacher=getattr(args, "teacher", None),
        aux_mount=getattr(args, "aux_mount", False),
    )


def one_thread_beside_workers(envs):
    """``envs``, with this process on one torch thread when they are CPU workers: the learner's small per-step
    ops run beside the stepping workers, and more threads only spin against them (a phase the workers sit out,
    such as a round of updates, can take the cores back with :func:`torch_threads`)."""
    if isinstance(envs, CPUVectorEnv):
        torch.set_num_threads(1)
    return envs


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads set to ``n`` for a phase the env workers sit out (e.g. a round of updates)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def shapes_of(space) -> tuple[Optional[tuple[int, int, int]], int]:
    """(image shape H,W,4 or None, state dim) of a single-env observation space (flattened rgbd or state)."""
    if isinstance(space, gym.spaces.Dict):
        rgb, depth, state = space["rgb"].shape, space["depth"].shape, space["state"].shape
        return (rgb[0], rgb[1], rgb[2] + depth[2]), state[0]
    return None, space.shape[0]
