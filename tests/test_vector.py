"""The CPU process-vector env behaves like ManiSkillVectorEnv: batched torch, auto-reset, final_info."""

from __future__ import annotations

import pytest
import torch

from maniskill_irb120.vector import make_vec_env

ENV = "TableClearing-IRB120-v1"


@pytest.fixture(scope="module")
def venv():
    env = make_vec_env(ENV, 2, backend="cpu", obs_mode="state", max_episode_steps=4)
    yield env
    env.close()


def test_batched_torch_interface(venv):
    obs, info = venv.reset(seed=3)
    assert isinstance(obs, torch.Tensor) and obs.shape[0] == 2
    assert venv.action_space.shape == (2, 5)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))
    assert rew.shape == (2,) and rew.dtype == torch.float32
    assert term.dtype == torch.bool and trunc.dtype == torch.bool
    assert "success" in info and info["success"].shape == (2,)
    assert info["episode"]["episode_len"].tolist() == [1, 1]


def test_auto_reset_reports_final_info_and_observation(venv):
    venv.reset(seed=5)
    for _ in range(4):  # max_episode_steps=4: the 4th step truncates both envs
        obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))
    assert trunc.all() or term.all()
    assert info["_final_info"].tolist() == [True, True]
    assert info["final_observation"].shape == obs.shape
    assert not torch.equal(info["final_observation"], obs)  # obs is already the next episode's first
    assert info["final_info"]["episode"]["episode_len"].tolist() == [4, 4]
    assert "success" in info["final_info"]
    # metrics restart with the new episode
    obs, *_, info = venv.step(torch.zeros(2, 5))
    assert info["episode"]["episode_len"].tolist() == [1, 1]


def test_final_observation_of_dict_obs_when_every_env_ends_at_once():
    """rgbd observations are nested dicts; with one worker every episode end is an 'all done' step."""
    env = make_vec_env(ENV, 1, backend="cpu", obs_mode="rgbd", max_episode_steps=2)
    try:
        env.reset(seed=0)
        for _ in range(2):
            obs, rew, term, trunc, info = env.step(torch.zeros(1, 5))
        assert bool(trunc[0] or term[0])
        final = info["final_observation"]
        rgb = final["sensor_data"]["hand_camera"]["rgb"]
        assert rgb.shape == obs["sensor_data"]["hand_camera"]["rgb"].shape == (1, 84, 84, 3)
        assert rgb.dtype == torch.uint8 and final["agent"]["qpos"].dtype == torch.float32
    finally:
        env.close()


def test_partial_reset_only_touches_selected_env(venv):
    venv.reset(seed=7)
    for _ in range(2):
        obs, *_ = venv.step(torch.zeros(2, 5))
    obs2, _ = venv.reset(options=dict(env_idx=torch.tensor([1])))
    assert torch.allclose(obs2[0], obs[0])
    assert not torch.allclose(obs2[1], obs[1])


def test_same_seed_same_initial_state(venv):
    a, _ = venv.reset(seed=11)
    b, _ = venv.reset(seed=11)
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a[0], a[1])  # workers get different seeds (seed + i)


def test_bad_inputs(venv):
    with pytest.raises(ValueError, match="shape"):
        venv.step(torch.zeros(3, 5))
    with pytest.raises(ValueError, match="backend"):
        make_vec_env(ENV, 2, backend="tpu")
    with pytest.raises(ValueError, match="CUDA"):
        if not torch.cuda.is_available():
            make_vec_env(ENV, 2, backend="gpu")
        else:
            raise ValueError("CUDA present: nothing to check")


def test_on_host_partial_reset_takes_host_indices():
    """Trainers hand OnHost host-side indices (lists, numpy); ManiSkill indexes its device buffers with
    env_idx as given, so OnHost must pass it on as a tensor on the env's device."""
    import gymnasium as gym
    import numpy as np

    from maniskill_irb120.vector import OnHost

    class Spy(gym.vector.VectorWrapper):
        def __init__(self, env):
            super().__init__(env)
            self.seen: list = []

        def reset(self, *, seed=None, options=None):
            self.seen.append((options or {}).get("env_idx"))
            return self.env.reset(seed=seed, options=options)

    inner = make_vec_env(ENV, 1, backend="inprocess", obs_mode="state", max_episode_steps=4)
    spy = Spy(inner)
    env = OnHost(spy)
    try:
        assert env.env_device == torch.device(inner.device)  # read through the wrapper, from the base env
        first, _ = env.reset(seed=21)
        for _ in range(2):
            moved, *_ = env.step(torch.ones(1, 5))
        assert not torch.allclose(moved, first)
        for idx in ([0], np.array([0])):
            again, _ = env.reset(seed=21, options=dict(env_idx=idx))
            got = spy.seen[-1]
            assert isinstance(got, torch.Tensor) and got.device == torch.device(inner.device)
            assert again.device.type == "cpu"
            torch.testing.assert_close(again, first)
    finally:
        env.close()
