"""Policies for ``sim2real-eval``: the task's scripted expert, or a trained checkpoint (``agents.ppo``,
``agents.dagger`` or ``agents.sac``) acting from its policy section alone (:mod:`maniskill_irb120.policies`), with
the sim env it expects (same obs layout and control mode on both sides)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.action import tcp_rotation, world_to_tool
from maniskill_irb120.envs.randomization import Randomization
from maniskill_irb120.errors import MissingFile, UsageError, nearest
from maniskill_irb120.experts import expert_for
from maniskill_irb120.policies import acting, read_policy_section
from maniskill_irb120.wrappers import observation_setup

MANIFEST_ENV = "MANISKILL_IRB120_POLICIES"
"""names a policies MANIFEST.json to read short names from (default: the repository's, when run from a checkout)"""
MANIFEST = Path("benchmarks") / "results" / "policies" / "MANIFEST.json"


def policy_manifests() -> list[Path]:
    """Where short policy names are looked up: ``$MANISKILL_IRB120_POLICIES``, else the committed
    ``benchmarks/results/policies/MANIFEST.json`` under the working directory or beside this source checkout."""
    import os

    if os.environ.get(MANIFEST_ENV):
        return [Path(os.environ[MANIFEST_ENV])]
    return [Path.cwd() / MANIFEST, Path(__file__).resolve().parents[2] / MANIFEST]


def resolve_policy(policy: str) -> str:
    """``policy`` as a file: 'expert' and existing files are returned as given; a short name (a key of a policies
    MANIFEST.json, e.g. ``camera-bf16-s1``) becomes its file, relative to the manifest's folder."""
    if policy == "expert" or Path(policy).is_file():
        return policy
    import json

    for manifest in policy_manifests():
        if manifest.is_file():
            entries = json.loads(manifest.read_text())["policies"]
            if policy in entries:
                return str(manifest.parent / entries[policy]["file"])
    manifests = [m for m in dict.fromkeys(policy_manifests()) if m.is_file()]  # from the checkout's root: one file
    names = sorted({n for m in manifests for n in json.loads(m.read_text())["policies"]})
    where = (
        f"nor a name in {' or '.join(map(str, manifests))}{nearest(policy, names)}"
        if manifests
        else f"and no policies MANIFEST.json to read names from (${MANIFEST_ENV} names one)"
    )
    listed = ", ".join(names[:5]) + (f", ... ({len(names)} in all)" if len(names) > 5 else "")
    raise MissingFile(
        f"--policy {policy!r}: neither 'expert' nor an existing checkpoint file, {where}"
        + (f"; its names: {listed}" if names else "")
    )


# how a checkpoint's action is chosen: as its trainer evaluated it (the section's eval_deterministic: agents.sac's
# --eval-deterministic; the others: the mean), the mean, or a sample of the policy's distribution (ppo, sac)
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
        return tcp_rotation(u.tcp_pose).cpu()
    return tcp_rotation(u.agent.tcp_pose.raw_pose).cpu()


def load_policy(
    policy: str,
    env_id: str,
    command_mode: str,
    actions: str = "as-trained",
    sim_shift: str | Randomization | None = None,
    expert_obs_mode: str = "rgbd",
) -> tuple[gym.Env, Callable[[gym.Env], object]]:
    """(sim env, policy factory taking the env the policy reads). ``policy``: 'expert', a checkpoint path or a
    committed policy's short name (:func:`resolve_policy`);
    ``actions``: one of :data:`ACTIONS`; ``sim_shift``: the sim side's own randomisation (the sim's model of a
    condition the real side is in), else the nominal task. ``expert_obs_mode``: the scripted expert reads the
    simulator, not its observation; ``state`` runs it without a camera on either side."""
    if actions not in ACTIONS:
        raise UsageError(f"--actions {actions!r}: use one of {', '.join(ACTIONS)}")
    if policy == "expert":
        if actions == "sample":
            raise UsageError("--actions sample: the scripted expert has no distribution to sample; use as-trained")
        shifted = {"randomization": sim_shift} if sim_shift else {}
        sim_env = gym.make(
            env_id, obs_mode=expert_obs_mode, control_mode="pd_ee_delta_tool", sim_backend="physx_cpu", **shifted
        )
        return sim_env, ExpertPolicy
    path = Path(resolve_policy(policy))
    section = read_policy_section(path, f"--policy {path}")
    if actions == "sample" and not section["stochastic"]:  # refused before a sim env is built
        raise UsageError(f"--actions sample: {path} is a {section['kind']} policy, deterministic; use as-trained")
    if section["env_id"] != env_id:
        raise UsageError(f"{path} was trained on {section['env_id']}, not {env_id}: give --env-id {section['env_id']}")
    control_mode = section["control_mode"]
    if command_mode == "tool_delta" and control_mode != "pd_ee_delta_tool":
        raise ValueError(f"{path} acts in {control_mode}; tool_delta sends pd_ee_delta_tool actions")
    env_kwargs = dict(section["env_kwargs"])
    # the sim side is the nominal task (or the condition sim_shift models), not the training distribution: a
    # policy trained with domain randomisation is compared with the sim it was meant for
    if env_kwargs.pop("randomization", None) is not None:
        env_kwargs.pop("reconfiguration_freq", None)  # it only served the randomisation's scene draws
    if sim_shift:
        env_kwargs["randomization"] = sim_shift
    if section["reward_mode"] is not None:
        env_kwargs.setdefault("reward_mode", section["reward_mode"])
    obs = "rgbd" if section["obs"] == "rgbd" else "state"
    obs_mode, obs_wrappers = observation_setup(obs, tuple(section["obs_without"]))
    kwargs = dict(obs_mode=obs_mode, control_mode=control_mode)
    sim_env = gym.make(env_id, sim_backend="physx_cpu", render_mode="rgb_array", **kwargs, **env_kwargs)
    for wrap in obs_wrappers:  # Sim2RealEnv applies the sim env's wrappers to the real side's observations too
        sim_env = wrap(sim_env)
    if obs == "rgbd":
        from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

        sim_env = FlattenRGBDObservationWrapper(sim_env)
    world_frame = section["action_frame"] == "world"
    sampled = actions == "sample" or (actions == "as-trained" and not section["eval_deterministic"])
    act = acting(section, sampled, torch.device("cpu"))
    return sim_env, lambda env: CheckpointPolicy(act, env, world_frame, sampled)
