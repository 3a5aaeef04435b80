"""The per-episode event rates every trainer logs (agents.common.EpisodeTracker), on the tasks' own physics."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401
from agents.common import EpisodeTracker
from maniskill_irb120.experts.pick_place import expert_for
from maniskill_irb120.experts.rollout import run_episode


@pytest.mark.parametrize("env_id, stage", [("GraspLift-IRB120-v1", "lifted"), ("StackCube-IRB120-v1", "stacked")])
def test_an_expert_episode_logs_the_stage_between_grasp_and_success(env_id, stage):
    """A learner that grasps but never succeeds must show which stage it stalls at: the expert's successful episode
    counts its grasp, its intermediate stage and its success once each; a random arm counts none of them."""
    env = gym.make(env_id, obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    try:
        tracker, rates = EpisodeTracker(1, "cpu"), {}

        def keep(_action, result):
            _, _, term, trunc, info = result
            rates.update(tracker.update(info, term | trunc))

        episode = run_episode(env, expert_for(env), seed=3, on_step=keep)
        assert episode.success
        assert rates["success_rate"] == [1.0] and rates["grasped_rate"] == [1.0] and rates[f"{stage}_rate"] == [1.0]
        assert rates["collided_rate"] == [0.0]

        env.reset(seed=4)
        gen, rates = torch.Generator().manual_seed(0), {}
        for _ in range(20):
            a = torch.rand(1, 5, generator=gen) * 2 - 1
            _, _, term, trunc, info = env.step(a)
            rates.update(tracker.update(info, torch.ones(1, dtype=torch.bool)))  # each step an "episode"
        assert rates[f"{stage}_rate"] == [0.0] and rates["success_rate"] == [0.0]
    finally:
        env.close()
