"""Policies for ``sim2real-eval``: the task's scripted expert, or a checkpoint of ``agents.ppo``, ``agents.dagger``
or ``agents.sac``, with the sim env each expects (same obs layout and control mode on both sides)."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.action import tcp_rotation, world_to_tool
from maniskill_irb120.experts import expert_for
from maniskill_irb120.wrappers import observation_setup

TRAINERS = {"maniskill_irb120.ppo/1": "ppo", "maniskill_irb120.dagger/1": "dagger", "maniskill_irb120.sac/1": "sac"}
# how a checkpoint's action is chosen: as its trainer evaluated it (agents.sac: its --eval-deterministic; the
# others: the mean), the mean, or a sample of the policy's distribution (agents.sac, agents.ppo)
ACTIONS = ("as-trained", "mean", "sample")


class ExpertPolicy:
    """The scripted expert reading ``env``'s state (the sim, or the twin behind the emulator)."""

    def __init__(self, env):
        self.expert = expert_for(env)

    def reset(self, seed: int | None = None) -> None:
        self.expert.reset()

    def act(self, obs) -> torch.Tensor:
        return self.expert.act()[0]


class CheckpointPolicy:
    """A trained agent. A world-frame policy (``agents.dagger``/``agents.sac`` default) is turned into the
    tool-frame action that goes over the wire with the TCP rotation of ``env``: the sim's, or on the real side
    the robot's (through the twin's kinematic copy, or the Sim2RealEnv's FK of the read joints).

    A sampling policy (``sampled``) draws its noise from a generator seeded by the episode's seed, apart from
    torch's global one, so the sim and the real side of one seed get the same draws: their gap is not noise."""

    def __init__(self, act: Callable[[dict], torch.Tensor], env=None, world_frame: bool = False, sampled: bool = False):
        self._act, self.env, self.world_frame, self.sampled = act, env, world_frame, sampled
        self._draws = np.random.default_rng(0)

    def reset(self, seed: int | None = None) -> None:
        self._draws = np.random.default_rng(seed)

    @torch.no_grad()
    def act(self, obs) -> torch.Tensor:
        obs = {"state": obs} if isinstance(obs, torch.Tensor) else obs
        if self.sampled:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(int(self._draws.integers(2**63)))
                a = self._act(obs)
        else:
            a = self._act(obs)
        a = a.reshape(1, -1).float().clamp(-1.0, 1.0)
        if self.world_frame:
            a = world_to_tool(a, _tcp_rot(self.env))
        return a[0]


def _tcp_rot(env) -> torch.Tensor:
    from maniskill_irb120.sim2real.env import IRB120Sim2RealEnv

    u = env.unwrapped
    if isinstance(u, IRB120Sim2RealEnv):  # FK of the joints the robot reported this step
        return tcp_rotation(u._tcp_pose).cpu()
    return tcp_rotation(u.agent.tcp_pose.raw_pose).cpu()


def _import_agents(name: str):
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # agents/ is training code in the repository, not in the installed package
    try:
        return __import__(f"agents.{name}", fromlist=[name])
    except ImportError:
        raise ImportError(f"checkpoint policies need agents/{name}.py: run from the repository's root") from None


def load_policy(
    policy: str, env_id: str, command_mode: str, actions: str = "as-trained"
) -> tuple[gym.Env, Callable[[gym.Env], object]]:
    """(sim env, policy factory taking the env the policy reads). ``policy``: 'expert' or a checkpoint path;
    ``actions``: one of :data:`ACTIONS`."""
    if actions not in ACTIONS:
        raise ValueError(f"--actions {actions!r}: use one of {', '.join(ACTIONS)}")
    if policy == "expert":
        if actions == "sample":
            raise ValueError("--actions sample: the scripted expert has no distribution to sample; use as-trained")
        sim_env = gym.make(env_id, obs_mode="rgbd", control_mode="pd_ee_delta_tool", sim_backend="physx_cpu")
        return sim_env, ExpertPolicy
    path = Path(policy)
    if not path.is_file():
        raise FileNotFoundError(f"--policy {policy!r}: neither 'expert' nor an existing checkpoint file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise ValueError(f"--policy {path} is not a readable torch checkpoint: {e}") from e
    fmt = ckpt.get("format") if isinstance(ckpt, dict) else None
    if fmt not in TRAINERS:
        raise ValueError(f"--policy {path}: format {fmt!r} is none of {sorted(TRAINERS)}")
    if fmt == "maniskill_irb120.dagger/1" and actions == "sample":  # refused before a sim env is built
        raise ValueError(f"--actions sample: {path} is an agents.dagger policy, deterministic; use as-trained")
    trainer = _import_agents(TRAINERS[fmt])
    args = trainer.Args(**{k: v for k, v in ckpt["args"].items() if k in trainer.Args.__dataclass_fields__})
    if args.env_id != env_id:
        raise ValueError(f"{path} was trained on {args.env_id}, not {env_id}")
    control_mode = getattr(args, "control_mode", "pd_ee_delta_tool")
    if command_mode == "tool_delta" and control_mode != "pd_ee_delta_tool":
        raise ValueError(f"{path} acts in {control_mode}; tool_delta sends pd_ee_delta_tool actions")
    env_kwargs = dict(args.env_kwargs)
    # the sim side is the nominal task: a policy trained with domain randomisation is compared with the sim
    # it was meant for, and the world's differences are the --shift's
    env_kwargs.pop("randomization", None)
    if hasattr(args, "reward_mode"):
        env_kwargs.setdefault("reward_mode", args.reward_mode)
    obs_mode, obs_wrappers = observation_setup(
        "rgbd" if args.obs == "rgbd" else "state", getattr(args, "obs_without", ())
    )
    kwargs = dict(obs_mode=obs_mode, control_mode=control_mode)
    sim_env = gym.make(env_id, sim_backend="physx_cpu", render_mode="rgb_array", **kwargs, **env_kwargs)
    for wrap in obs_wrappers:  # Sim2RealEnv applies the sim env's wrappers to the real side's observations too
        sim_env = wrap(sim_env)
    if args.obs == "rgbd":
        from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

        sim_env = FlattenRGBDObservationWrapper(sim_env)
    world_frame = getattr(args, "action_frame", "tool") == "world"
    sampled = actions == "sample" or (actions == "as-trained" and not getattr(args, "eval_deterministic", True))
    if fmt == "maniskill_irb120.ppo/1":
        agent = trainer.agent_from_checkpoint(ckpt, torch.device("cpu"))
        act = lambda obs: agent.get_action(obs, deterministic=not sampled)  # noqa: E731
    elif fmt == "maniskill_irb120.dagger/1":
        act = trainer.policy_from_checkpoint(ckpt, torch.device("cpu"))
    else:  # with a reference, sampling explores around the clone as in training (its --init-std)
        model = trainer.model_from_checkpoint(ckpt, torch.device("cpu"))
        act = lambda obs: model.act(obs, deterministic=not sampled, noise=args.init_std)  # noqa: E731
    return sim_env, lambda env: CheckpointPolicy(act, env, world_frame, sampled)
