"""Env wrappers the library configs in ``agents/configs`` name, for any library (SB3, skrl) over these tasks.

:class:`AbsorbingSuccess` is what the project's PPO does with ``--absorbing-success``, moved into the env so a
library whose learner treats every termination as worth nothing afterwards (SB3's, skrl's) sees it too: a success
ends the episode, and without it holding the object (~0.9 a step, forever) outvalues delivering it (1, once).
:class:`ActionPenalty` is the action-magnitude cost HER's DDPG puts on its actor (``action_l2``), as a reward term:
a deterministic actor that found a reward by pushing at full command pins its actions at the bounds, where noise is
clipped back and a slow hold is never tried (docs/notes/library-algorithms-on-grasplift.md, TD3).
Each wrapper wraps one task env (batched torch tensors, as ``make_vector_env``'s ``wrappers`` take them) and pickles,
so CPU worker processes can build it; rl-zoo3's ``env_wrapper`` entries name it with its keywords.
"""

from __future__ import annotations

import gymnasium as gym
import torch

from maniskill_irb120.action import ACTION_DIM


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


class ActionPenalty(gym.Wrapper):
    """Subtract ``coef`` times the mean square of the arm's action components (``[dx, dy, dz, yaw]``, clipped to
    [-1, 1] as the controller clips them) from every step's reward; the gripper's is left out, since holding it
    closed at -1 is how a grasp is kept. A shaping term a config opts into, labelled as such: the task's reward and
    its success are unchanged, and held-out evaluation reads the success."""

    ARM = ACTION_DIM - 1

    def __init__(self, env: gym.Env, coef: float):
        if not (coef >= 0.0 and coef < float("inf")):
            raise ValueError(f"ActionPenalty coef must be a finite number >= 0, got {coef}")
        super().__init__(env)
        self.coef = float(coef)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        r = torch.as_tensor(reward)
        a = torch.as_tensor(action, device=r.device).to(r.dtype if r.is_floating_point() else torch.float32)
        if a.shape[-1] != ACTION_DIM:
            raise ValueError(f"ActionPenalty expects actions of {ACTION_DIM} components, got shape {tuple(a.shape)}")
        cost = self.coef * a[..., : self.ARM].clamp(-1.0, 1.0).square().mean(-1)
        return obs, r - cost.reshape(r.shape), terminated, truncated, info
