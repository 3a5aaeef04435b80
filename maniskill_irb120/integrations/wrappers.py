"""Env wrappers the library configs in ``agents/configs`` name, for any library (SB3, skrl) over these tasks.

:class:`AbsorbingSuccess` is what the project's PPO does with ``--absorbing-success``, moved into the env so a
library whose learner treats every termination as worth nothing afterwards (SB3's, skrl's) sees it too: a success
ends the episode, and without it holding the object (~0.9 a step, forever) outvalues delivering it (1, once).
Each wrapper wraps one task env (batched torch tensors, as ``make_vector_env``'s ``wrappers`` take them) and pickles,
so CPU worker processes can build it; rl-zoo3's ``env_wrapper`` entries name it with its keywords.
"""

from __future__ import annotations

import gymnasium as gym
import torch


class AbsorbingSuccess(gym.Wrapper):
    """On the step a success terminates an episode, add ``gamma / (1 - gamma) * reward_max`` to its reward.

    That is the discounted value of staying in an absorbing state paying ``reward_max`` a step for ever, so a learner
    that bootstraps a terminated episode with zero gets the same return as one that bootstraps it with the absorbing
    value (``agents.ppo --absorbing-success``; ManiSkill's max-reward convention). ``gamma`` must be the learner's.
    ``reward_max``: the reward mode's most a step (``normalized_dense``: 1). Collisions and truncations are untouched.
    """

    def __init__(self, env: gym.Env, gamma: float, reward_max: float = 1.0):
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {gamma}")
        super().__init__(env)
        self.gamma, self.reward_max = float(gamma), float(reward_max)
        self.bonus = self.gamma / (1.0 - self.gamma) * self.reward_max

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        success = info.get("success")
        if success is not None:
            done = torch.as_tensor(success, device=torch.as_tensor(reward).device).bool()
            done = done & torch.as_tensor(terminated, device=done.device).bool()
            reward = reward + self.bonus * done.to(torch.as_tensor(reward).dtype)
        return obs, reward, terminated, truncated, info
