"""The table tasks' shared base env (``envs/base.py``): per-env episode randomness in batched (GPU) resets,
observations that are copies of the env's state, the default reward mode. Short, seeded runs only.

ManiSkill's CPU sim has one env, so where a batch is needed the test drives ManiSkill's own functions
(``BaseEnv._set_main_rng`` / ``_set_episode_rng``) on a stand-in with a batch of 4 envs.
"""

from __future__ import annotations

from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.envs.sapien_env import BaseEnv

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.envs.base import IRB120TableEnv

ENV = "TableClearing-IRB120-v1"


# ---------------------------------------------------------- per-env episode randomness (the GPU path, on CPU tensors)
def batch_of_envs(num_envs: int) -> SimpleNamespace:
    """What ManiSkill's RNG methods and our ``_episode_draws`` read, for a batch of envs."""
    return SimpleNamespace(
        num_envs=num_envs,
        device=torch.device("cpu"),
        _enhanced_determinism=True,
        _main_seed=None,
        _episode_seed=None,
        _batched_episode_rng=None,
        _batched_rng_backend="numpy:random_state",
    )


def ms_reset_rng(fake, seed, env_idx) -> torch.Tensor:
    """ManiSkill 3.0.1's RNG steps of ``BaseEnv.reset`` (no reconfiguration), then our per-env draws."""
    BaseEnv._set_main_rng(fake, seed)
    BaseEnv._set_episode_rng(fake, seed, env_idx)
    draws = IRB120TableEnv._episode_draws(fake, env_idx, joint_noise=6, obj_xy=2, obj_yaw=1)
    return torch.cat(list(draws.values()), 1)


def test_partial_resets_draw_a_new_start_for_each_env():
    fake = batch_of_envs(4)
    ms_reset_rng(fake, 0, torch.arange(4))
    idx = torch.tensor([1, 2, 3])  # env 0 keeps running
    first, second = ms_reset_rng(fake, None, idx), ms_reset_rng(fake, None, idx)
    assert first.shape == (3, 9)
    assert not torch.allclose(first, second)  # each auto-reset of an env draws anew
    assert len({tuple(r.tolist()) for r in torch.cat([first, second])}) == 6
    # the defect this replaces: ManiSkill seeds torch with env 0's episode seed before every reset
    with torch.random.fork_rng():
        torch.manual_seed(int(fake._episode_seed[0]))
        a = torch.rand(3, 9)
        torch.manual_seed(int(fake._episode_seed[0]))
        assert torch.equal(a, torch.rand(3, 9))


def test_batched_draws_equal_single_env_draws_with_the_same_seeds():
    """GPU env i with episode seed s_i starts where a CPU env reset with seed s_i starts."""
    fake = batch_of_envs(3)
    batched = ms_reset_rng(fake, [10, 11, 12], torch.arange(3))
    env = gym.make(ENV, obs_mode="state")
    u = env.unwrapped
    for i, s in enumerate((10, 11, 12)):
        env.reset(seed=s)
        span = 0.08 - u.spawn_margin
        expect_xy = (batched[i, 6:8] * 2 - 1) * span + torch.tensor([0.35, 0.13])
        torch.testing.assert_close(u.obj.pose.p[0, :2], expect_xy, atol=1e-5, rtol=0)
    env.close()


# --------------------------------------------------------------------------- observations are copies
def _leaves(d: dict, prefix: str = ""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}/")
        else:
            yield f"{prefix}{k}", v


def test_state_dict_observations_do_not_alias_env_state():
    """Writing into every observation tensor changes nothing the env keeps (trays, poses, info, the grasp
    reference of the next step), for reset and step observations alike."""
    e = gym.make(ENV, obs_mode="state_dict")
    try:
        u = e.unwrapped
        for obs, info in (e.reset(seed=0), e.step(np.zeros(5))[::4]):
            kept = dict(
                source=u.source_center.clone(),
                dest=u.dest_center.clone(),
                tcp=u.tcp_pose.clone(),
                obj=u.step_state["obj_pose"].clone(),
                grasped=info["grasped"].clone(),
                cur={k: v.clone() for k, v in u._cur.items()},
            )
            for _, v in _leaves(obs):
                v.fill_(True) if v.dtype == torch.bool else v.fill_(5)
            torch.testing.assert_close(u.source_center, kept["source"])
            torch.testing.assert_close(u.dest_center, kept["dest"])
            torch.testing.assert_close(u.tcp_pose, kept["tcp"])
            torch.testing.assert_close(u.step_state["obj_pose"], kept["obj"])
            torch.testing.assert_close(info["grasped"], kept["grasped"])
            for k, v in u._cur.items():
                torch.testing.assert_close(v, kept["cur"][k])
    finally:
        e.close()


def test_gymnasium_env_checker_with_state_dict_obs():
    """gymnasium's checker asserts that reset and step observations share no data (it failed on state_dict)."""
    from gymnasium.utils.env_checker import check_env
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    e = CPUGymWrapper(gym.make(ENV, obs_mode="state_dict"))
    try:  # skip_close_check: see test_table_clearing.test_gymnasium_env_checker
        check_env(e, skip_render_check=True, skip_close_check=True)
    finally:
        e.close()


# --------------------------------------------------------------------------- default reward mode
def test_default_reward_is_normalized_dense_and_the_seeds_reward_is_one_keyword_away():
    from maniskill_irb120.envs.table_clearing import REWARD_TERMS

    default, dense = gym.make(ENV, obs_mode="state"), gym.make(ENV, obs_mode="state", reward_mode="dense")
    try:
        assert default.unwrapped.reward_mode == "normalized_dense" and dense.unwrapped.reward_mode == "dense"
        for e in (default, dense):
            e.reset(seed=0)
        action = [0.0, 0.0, 0.0, 0.0, 1.0]
        _, r_norm, *_ = default.step(action)
        _, r_dense, *_, info = dense.step(action)
        assert 0.0 <= float(r_norm[0]) <= 1.0
        assert float(r_dense[0]) == pytest.approx(sum(float(info[k][0]) for k in REWARD_TERMS))
        assert float(info["r_time"][0]) == -1.0
    finally:
        default.close()
        dense.close()
