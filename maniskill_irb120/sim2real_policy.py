"""Policies for ``sim2real-eval``: the task's scripted expert, or an ``agents.ppo`` checkpoint, with the sim env
each expects (same obs layout and control mode on both sides)."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import torch

from maniskill_irb120.expert import expert_for


class ExpertPolicy:
    """The scripted expert reading ``env``'s state (the sim, or the twin behind the emulator)."""

    def __init__(self, env):
        self.expert = expert_for(env)

    def reset(self) -> None:
        self.expert.reset()

    def act(self, obs) -> torch.Tensor:
        return self.expert.act()[0]


class CheckpointPolicy:
    """An ``agents.ppo`` agent, deterministic (its mean action)."""

    def __init__(self, agent, flatten: Callable):
        self.agent, self.flatten = agent, flatten

    def reset(self) -> None:
        pass

    @torch.no_grad()
    def act(self, obs) -> torch.Tensor:
        return self.agent.get_action(self.flatten(obs), deterministic=True)[0].clamp(-1.0, 1.0)


def load_policy(policy: str, env_id: str, command_mode: str) -> tuple[gym.Env, Callable[[gym.Env], object]]:
    """(sim env, policy factory taking the env the policy reads). ``policy``: 'expert' or a checkpoint path."""
    if policy == "expert":
        sim_env = gym.make(env_id, obs_mode="rgbd", control_mode="pd_ee_delta_tool", sim_backend="physx_cpu")
        return sim_env, ExpertPolicy
    path = Path(policy)
    if not path.is_file():
        raise FileNotFoundError(f"--policy {policy!r}: neither 'expert' nor an existing checkpoint file")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # agents/ is training code in the repository, not in the installed package
    try:
        from agents import ppo
    except ImportError:
        raise ImportError("checkpoint policies need agents/ppo.py: run from the repository's root directory") from None
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict) or ckpt.get("format") != "maniskill_irb120.ppo/1":
        raise ValueError(f"{path} is not an agents.ppo checkpoint")
    args = ppo.Args(**{k: v for k, v in ckpt["args"].items() if k in ppo.Args.__dataclass_fields__})
    if args.env_id != env_id:
        raise ValueError(f"{path} was trained on {args.env_id}, not {env_id}")
    if command_mode == "tool_delta" and args.control_mode != "pd_ee_delta_tool":
        raise ValueError(f"{path} acts in {args.control_mode}; tool_delta sends pd_ee_delta_tool actions")
    kwargs = dict(obs_mode="rgbd" if args.obs == "rgbd" else "state", control_mode=args.control_mode)
    sim_env = gym.make(env_id, sim_backend="physx_cpu", render_mode="rgb_array", **kwargs, **args.env_kwargs)
    if args.obs == "rgbd":
        from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

        sim_env = FlattenRGBDObservationWrapper(sim_env)
    sig = ckpt["signature"]
    agent = ppo.Agent(tuple(sig["image_shape"]) if sig["image_shape"] else None, sig["state_dim"], sig["action_dim"])
    agent.load_state_dict(ckpt["model"])
    agent.eval()
    return sim_env, lambda env: CheckpointPolicy(agent, ppo.flatten_obs)
