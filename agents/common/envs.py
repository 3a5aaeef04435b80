"""The envs trainers collect from and the observations they read: batched torch obs as a dict, devices, the
policy's action-frame wrappers, and the labelled vector envs of the imitation and demo-seeded trainers."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from typing import Optional

import gymnasium as gym
import torch

from maniskill_irb120.action import tcp_rotation, tool_to_world
from maniskill_irb120.envs.base import grasp_yaw_error
from maniskill_irb120.experts import expert_for
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


def privileged_aux(env: gym.Env, frame: str = "world") -> torch.Tensor:
    """(N, 5) what a camera policy has to find in its image: the object's position relative to the TCP (in the
    learner's action frame: world or tool axes; in decimetres, so about unit scale) and the grasp yaw error as
    sin/cos of four times it (continuous across the cube's 90° symmetry)."""
    u = env.unwrapped
    obj, tcp = u.target_object.pose.raw_pose, u.tcp_pose  # the task's declared interface (envs/base.py)
    rel = (obj[:, :3] - tcp[:, :3]) * 10.0
    if frame == "tool":  # the hand camera's own axes: an offset in the image is one in the tool frame
        rel = (tcp_rotation(tcp).transpose(1, 2) @ rel.unsqueeze(2)).squeeze(2)
    yaw = 4.0 * grasp_yaw_error(obj, tcp)
    return torch.cat([rel, yaw.sin()[:, None], yaw.cos()[:, None]], dim=1).float()


class ExpertLabels(gym.Wrapper):
    """Puts the reactive expert's action for the state just reached into ``info["expert_action"]``, in the
    learner's action frame (``world``: its translation rotated out of the tool frame), and with ``aux`` the
    auxiliary targets (:func:`privileged_aux`) into ``info["expert_aux"]``."""

    def __init__(self, env: gym.Env, frame: str = "tool", aux: bool = False):
        super().__init__(env)
        if frame not in ("tool", "world"):
            raise ValueError(f"unknown action frame {frame!r}; expected 'tool' or 'world'")
        if aux and getattr(env.unwrapped, "target_object", None) is None:
            raise ValueError(
                f"--aux-weight needs a task that declares a target_object; {env.unwrapped.spec.id} does not"
            )
        self.expert = expert_for(env, reactive=True)
        self.frame, self.aux = frame, aux

    def _label(self, info: dict) -> None:
        a = self.expert.act()
        info["expert_action"] = (
            tool_to_world(a, tcp_rotation(self.env.unwrapped.agent.tcp_pose.raw_pose)) if self.frame == "world" else a
        )
        if self.aux:
            info["expert_aux"] = privileged_aux(self.env, self.frame)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.expert.reset((kwargs.get("options") or {}).get("env_idx"))  # a batched env resets ended envs only
        self._label(info)
        return obs, info

    def step(self, action):
        obs, rew, term, trunc, info = self.env.step(action)
        self._label(info)
        return obs, rew, term, trunc, info


def action_wrappers(frame: str) -> list:
    """The wrappers between a policy in ``frame`` and the tool-frame env (``world``: WorldFrameToolAction)."""
    return [WorldFrameToolAction] if frame == "world" else []


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
):
    """``num_envs`` envs whose info carries the reactive expert's label for every state (:class:`ExpertLabels`;
    with ``aux`` the auxiliary targets too), in the policy's observation and action frame, as host tensors."""
    obs_mode, obs_wrappers = observation_setup(obs, obs_without)
    kwargs = dict(obs_mode=obs_mode, control_mode="pd_ee_delta_tool", **(env_kwargs or {}))
    if obs == "rgbd":
        kwargs["render_mode"] = "rgb_array"
    else:
        kwargs.setdefault("render_backend", "none")
    labels = partial(ExpertLabels, frame=action_frame, aux=aux)
    wrappers = [*obs_wrappers, *action_wrappers(action_frame), labels]
    if obs == "rgbd":
        from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

        wrappers.insert(len(obs_wrappers), FlattenRGBDObservationWrapper)
    backend = "inprocess" if backend == "cpu" and num_envs == 1 else backend  # auto: make_vec_env's
    envs = one_thread_beside_workers(
        make_vec_env(env_id, num_envs, backend=backend, wrappers=wrappers, record_metrics=True, **kwargs)
    )
    # the dataset and the replay live in host memory: a batched env's tensors come back to the CPU each step
    return envs if isinstance(envs, CPUVectorEnv) else OnHost(envs)


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
