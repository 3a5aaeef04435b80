"""Writes reward_trajectories.npz beside this file: for every task and reward mode, two seeded episodes (the expert
with noise on its arm actions for its first steps, and uniform random actions) with each step's action, reward and
every numeric ``info`` entry, as the envs compute them when it was written. ``tests/envs/test_reward_regression.py``
replays the actions and asks for the same numbers to float32 rounding (its RTOL and ATOL: another CPU differs in the
last bits), so a change meant to be a speed-up cannot change what a learner sees. Run it again only for a change
that is meant to change rewards, terms or events, and say so in the commit:

    .venv/bin/python tests/envs/data/reward_trajectories.py
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.experts import expert_for

TASKS = ("TableClearing-IRB120-v1", "GraspLift-IRB120-v1", "StackCube-IRB120-v1")
REWARD_MODES = ("normalized_dense", "dense", "sparse")
EPISODES = (("expert", 11), ("random", 12))  # (actor, seed)
MAX_STEPS = 120
NOISY_STEPS = 40
OUT = Path(__file__).with_name("reward_trajectories.npz")


def make_env(env_id: str, reward_mode: str) -> gym.Env:
    return gym.make(env_id, obs_mode="state", reward_mode=reward_mode, render_backend="none")


def numeric_info(info: dict) -> dict[str, np.ndarray]:
    """The (1,)-shaped tensors of ``info`` (rewards' terms, events, flags) as float64 scalars."""
    return {
        k: v.double().numpy()[0]
        for k, v in info.items()
        if isinstance(v, torch.Tensor) and v.shape == (1,) and k != "elapsed_steps"
    }


def actions_for(env: gym.Env, actor: str, seed: int) -> list[torch.Tensor]:
    """The episode's actions, chosen on a normalized_dense env (the actions do not depend on the reward mode)."""
    g = torch.Generator().manual_seed(seed)
    env.reset(seed=seed)
    expert = expert_for(env, reactive=True)
    expert.reset(None)
    actions = []
    for t in range(MAX_STEPS):
        if actor == "expert":
            a = expert.act().clone()
            if t < NOISY_STEPS:  # then clean, so that the episode can also hold still and succeed
                a[:, :4] += 0.15 * torch.randn(1, 4, generator=g)
            a = a.clamp(-1, 1)
        else:
            a = torch.rand(1, 5, generator=g) * 2 - 1
        actions.append(a)
        _, _, term, trunc, _ = env.step(a)
        if bool(term[0] or trunc[0]):
            break
    return actions


def record(env_id: str, reward_mode: str, actor: str, seed: int, actions: list[torch.Tensor]) -> dict[str, np.ndarray]:
    env = make_env(env_id, reward_mode)
    env.reset(seed=seed)
    rows: dict[str, list] = {"reward": []}
    for a in actions:
        _, reward, _, _, info = env.step(a)
        rows["reward"].append(float(reward.double()[0]))
        for k, v in numeric_info(info).items():
            rows.setdefault(k, []).append(v)
    env.close()
    return {k: np.asarray(v, dtype=np.float64) for k, v in rows.items()}


def main() -> None:
    data = {}
    for env_id in TASKS:
        for actor, seed in EPISODES:
            env = make_env(env_id, "normalized_dense")
            actions = actions_for(env, actor, seed)
            env.close()
            key = f"{env_id}/{actor}/{seed}"
            data[f"{key}/actions"] = torch.cat(actions).numpy()
            for mode in REWARD_MODES:
                for k, v in record(env_id, mode, actor, seed, actions).items():
                    data[f"{key}/{mode}/{k}"] = v
    np.savez_compressed(OUT, **data)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes, {len(data)} arrays)")


if __name__ == "__main__":
    main()
