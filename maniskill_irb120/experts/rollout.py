"""One episode loop for everything that rolls a scripted expert out: the expert's success check, demo
collection and the demo video. Each caller adds what it needs through ``on_step``."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import gymnasium as gym
import torch
from mani_skill.utils.registration import REGISTERED_ENVS

from maniskill_irb120.envs import table_clearing
from maniskill_irb120.errors import UsageError
from maniskill_irb120.experts.pick_place import PHASE_NAMES, PickPlaceExpert, expert_for


@dataclass
class Episode:
    seed: int
    success: bool
    steps: int
    truncated: bool
    info: dict
    failure: str | None = None
    events: Counter = field(default_factory=Counter)


def run_episode(
    env: gym.Env,
    expert: PickPlaceExpert,
    seed: int,
    max_steps: int | None = None,
    on_step: Callable[[torch.Tensor, tuple], None] | None = None,
) -> Episode:
    """Reset ``env`` to ``seed`` and step ``expert`` until the episode ends (or ``max_steps``).
    ``on_step(action, step_result)`` runs after every step; one env (num_envs=1)."""
    env.reset(seed=seed)
    expert.reset()
    limit = max_steps or env.spec.max_episode_steps or REGISTERED_ENVS[env.unwrapped.spec.id].max_episode_steps
    events: Counter = Counter()
    info, term, trunc, t, was_grasped = {}, False, False, 0, False
    while t < limit:
        t += 1
        action = expert.act()
        result = env.step(action)
        _, _, term_t, trunc_t, info = result
        grasped = bool(info["grasped"][0])
        events["grasp"] += int(grasped and not was_grasped)
        events["dropped"] += int(bool(info.get("dropped", torch.zeros(1))[0]))
        was_grasped = grasped
        if on_step is not None:
            on_step(action, result)
        term, trunc = bool(term_t[0]), bool(trunc_t[0])
        if term or trunc:
            break
    truncated = not term
    success = bool(info["success"][0])
    failure = None
    if not success:
        phase = PHASE_NAMES[int(expert.phase[0])]
        failure = f"collision during {phase}" if bool(info["fail"][0]) else f"timeout during {phase}"
    return Episode(seed, success, t, truncated, info, failure, events)


def run_expert(
    env_id: str = table_clearing.ENV_ID,
    episodes: int = 100,
    seed: int = 0,
    obs_mode: str = "state",
    max_steps: int | None = None,
    record: bool = False,
    reactive: bool = False,
    **env_kwargs,
) -> dict:
    """The task's scripted expert for ``episodes`` single-env episodes seeded ``seed, seed+1, ...``.

    Returns success_rate, episodes, mean_steps (over all episodes), failure reason counts, steps/s and,
    with ``record``, per-episode actions and TCP positions (for determinism checks)."""
    if episodes < 1:
        raise UsageError(f"--episodes {episodes}: give a whole number >= 1")
    env = gym.make(env_id, obs_mode=obs_mode, control_mode="pd_ee_delta_tool", **env_kwargs)
    expert = expert_for(env, reactive=reactive)
    runs, trajs = [], []
    t0 = time.perf_counter()
    for ep in range(episodes):
        actions, tcps = [], []

        def keep(action, _result, actions=actions, tcps=tcps):
            actions.append(action[0].cpu().clone())
            tcps.append(env.unwrapped.agent.tcp_pose.p[0].cpu().clone())

        runs.append(run_episode(env, expert, seed + ep, max_steps, keep if record else None))
        if record:
            trajs.append(dict(actions=torch.stack(actions), tcp=torch.stack(tcps), success=runs[-1].success))
    elapsed = time.perf_counter() - t0
    env.close()
    steps = [r.steps for r in runs]
    out = dict(
        env_id=env_id,
        success_rate=sum(r.success for r in runs) / episodes,
        episodes=episodes,
        seed=seed,
        mean_steps=sum(steps) / episodes,
        max_steps=max(steps),
        failures=dict(Counter(r.failure for r in runs if r.failure)),
        failed_seeds=[r.seed for r in runs if not r.success],
        grasp_events=sum(r.events["grasp"] for r in runs),
        drop_events=sum(r.events["dropped"] for r in runs),
        steps_per_s=sum(steps) / elapsed,
        wall_s=elapsed,
    )
    if record:
        out["trajectories"] = trajs
    return out
