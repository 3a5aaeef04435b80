"""Wrappers a learner puts around a task: world-frame translation for the tool action, and observation filters.

The original report's action moves the TCP along its own axes. Which world direction a tool-axis command
means depends on the tool's yaw, which changes every episode (the gripper turns to the object's faces), so
"move towards the tray" is a product of the tool's rotation and a world vector: a bilinear map an MLP
regresses poorly (docs/notes/state-recipes.md). ManiSkill's own EE controllers offer
the same choice (``frame="root_translation:..."``). :class:`WorldFrameToolAction` takes the translation in
world axes and rotates it into the tool frame before the controller, so the executed action is still a
``pd_ee_delta_tool`` action within its limits (the real-robot adapter and its safety envelope see nothing new).

Both frames are ``maniskill_irb120.action``'s layout; the conversion is its ``world_to_tool``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.action import ACTION_DIM, tcp_rotation, world_to_tool


class WorldFrameToolAction(gym.ActionWrapper):
    """Wrap a ``pd_ee_delta_tool`` env so its translation commands are in world axes (see the module doc)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        mode = env.unwrapped.control_mode
        if mode != "pd_ee_delta_tool":
            raise ValueError(f"WorldFrameToolAction needs control_mode='pd_ee_delta_tool', the env runs {mode!r}")

    def action(self, action):
        u = self.env.unwrapped
        a = torch.as_tensor(np.asarray(action) if not isinstance(action, torch.Tensor) else action)
        a = a.to(device=u.device, dtype=torch.float32)
        single = a.ndim == 1
        a = a.reshape(1, -1) if single else a
        if a.shape[-1] != ACTION_DIM:
            raise ValueError(f"expected actions of shape (5,) or (N, 5), got {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            raise ValueError("action contains NaN or inf")
        out = world_to_tool(a.clamp(-1, 1), tcp_rotation(u.agent.tcp_pose.raw_pose))
        return out[0] if single else out


class DropObservationKeys(gym.ObservationWrapper):
    """Leave out of the observation what a real robot cannot measure, e.g. ``agent/qvel``: the IRB 120's RAPID
    protocol carries joint angles only, and a sim's settled joint speeds (std < 0.005 rad/s) are what a
    state-normalised policy learns to key on. On ``obs_mode="state_dict"`` the rest is flattened exactly as
    ``obs_mode="state"`` would; on ``"rgbd"`` the dict goes on (``FlattenRGBDObservationWrapper`` after this)."""

    def __init__(self, env: gym.Env, keys: tuple[str, ...] | list[str]):
        super().__init__(env)
        u = env.unwrapped
        if u.obs_mode not in ("state_dict", "rgbd"):
            raise ValueError(f"DropObservationKeys needs obs_mode 'state_dict' or 'rgbd', the env has {u.obs_mode!r}")
        self.paths = [tuple(str(k).split("/")) for k in keys]
        if not self.paths:
            raise ValueError("DropObservationKeys needs at least one key such as 'agent/qvel'")
        for path in self.paths:
            node = u._init_raw_obs
            for i, name in enumerate(path):
                if not isinstance(node, dict) or name not in node:
                    have = sorted(node) if isinstance(node, dict) else []
                    raise ValueError(f"observation has no {'/'.join(path)!r}: {'/'.join(path[:i]) or 'top'} has {have}")
                node = node[name]
        u.update_obs_space(self.observation(u._init_raw_obs))

    def observation(self, obs: dict):
        from mani_skill.utils.common import flatten_state_dict

        for path in self.paths:
            obs = _without(obs, path)
        if self.env.unwrapped.obs_mode == "state_dict":
            return flatten_state_dict(obs, use_torch=True, device=self.env.unwrapped.device)
        return obs


def _without(d: dict, path: tuple[str, ...]) -> dict:
    """A copy of nested dict ``d`` without ``path`` (the caller's dict untouched)."""
    out = dict(d)
    if len(path) == 1:
        out.pop(path[0], None)
    else:
        out[path[0]] = _without(d[path[0]], path[1:])
    return out


def observation_setup(obs: str, without: Sequence[str] = ()) -> tuple[str, list]:
    """(``obs_mode`` for ``gym.make``, observation wrappers innermost first) for a policy on ``obs`` ('state' or
    'rgbd') that does not see the keys ``without`` -- the one definition trainers and sim2real-eval share."""
    if not without:
        return obs, []
    return ("state_dict" if obs == "state" else obs), [partial(DropObservationKeys, keys=tuple(without))]
