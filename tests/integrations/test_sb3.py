"""Stable-Baselines3 on the tasks through maniskill_irb120.integrations.sb3: SB3's own env checker passes, PPO and SAC
run on the CPU workers from state and from the camera, and a partial reset reaches SB3 as a new episode with the right
final observation and Monitor-style statistics."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from stable_baselines3 import PPO, SAC  # noqa: E402
from stable_baselines3.common.env_checker import check_env  # noqa: E402
from stable_baselines3.common.preprocessing import is_image_space  # noqa: E402
from stable_baselines3.common.torch_layers import NatureCNN  # noqa: E402

from maniskill_irb120.integrations.observations import DEPTH_MM_PER_LEVEL  # noqa: E402
from maniskill_irb120.integrations.sb3 import IRB120SB3VecEnv, make_sb3_env, make_sb3_vec_env  # noqa: E402
from maniskill_irb120.vector import TORCH_THREADS  # noqa: E402

ENV = "GraspLift-IRB120-v1"


@pytest.mark.parametrize("obs", ["state", "rgbd"])
def test_sb3_check_env_passes_without_a_warning(obs):
    env = make_sb3_env(ENV, obs)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # SB3's checker warns about what would not work (e.g. image bounds)
            check_env(env, warn=True)
        if obs == "rgbd":
            space = env.observation_space
            assert set(space.spaces) == {"image", "state"}
            assert space["image"].shape == (4, 84, 84) and is_image_space(space["image"], check_channels=True)
            o, _ = env.reset(seed=0)
            raw = env.unwrapped.get_obs()  # the task's own camera frame of the same state
            rgb = raw["sensor_data"]["hand_camera"]["rgb"][0].permute(2, 0, 1).numpy()
            depth_mm = raw["sensor_data"]["hand_camera"]["depth"][0, :, :, 0].numpy().astype(float)
            assert np.array_equal(o["image"][:3], rgb)
            expected = np.clip(np.floor((depth_mm + DEPTH_MM_PER_LEVEL // 2) / DEPTH_MM_PER_LEVEL), 0, 255)
            assert np.array_equal(o["image"][3], expected.astype(np.uint8))
            assert 0 < o["image"][3].min() < o["image"][3].max() < 255  # the depth range is inside the 0-510 mm
    finally:
        env.close()


def test_unknown_obs_and_backend_are_named():
    with pytest.raises(ValueError, match="unknown obs 'pixels'"):
        make_sb3_vec_env(ENV, 2, "pixels")
    with pytest.raises(ValueError, match="unknown backend 'tpu'"):
        make_sb3_vec_env(ENV, 2, "state", backend="tpu")
    with pytest.raises(ValueError, match="reward_mode='shaped' is not supported"):
        make_sb3_env(ENV, "state", reward_mode="shaped")


def threads_seen_while_stepping(venv: IRB120SB3VecEnv) -> list[int]:
    """torch's thread count in this process each time the CPU envs underneath step or reset."""
    seen: list[int] = []
    inner = venv.vector_env
    step, reset = inner.step, inner.reset
    inner.step = lambda a: (seen.append(torch.get_num_threads()), step(a))[1]
    inner.reset = lambda **kw: (seen.append(torch.get_num_threads()), reset(**kw))[1]
    return seen


@pytest.mark.parametrize("obs, given, learner", [("state", None, 1), ("rgbd", None, TORCH_THREADS), ("state", 3, 3)])
def test_one_torch_thread_while_the_envs_step_and_the_learners_between_steps(obs, given, learner):
    """Env 0 steps in this process beside the workers on one thread; the learner gets its threads back after."""
    before = torch.get_num_threads()
    venv = make_sb3_vec_env(ENV, 2, obs, backend="cpu", seed=0, learner_threads=given)
    try:
        seen = threads_seen_while_stepping(venv)
        assert torch.get_num_threads() == learner
        venv.reset()
        assert torch.get_num_threads() == learner
        venv.step(np.zeros((2, 5), dtype=np.float32))
        assert seen == [1, 1] and torch.get_num_threads() == learner
        with pytest.raises(ValueError, match="NaN or inf"):  # a refused step hands the threads back too
            venv.step(np.full((2, 5), np.nan, dtype=np.float32))
        assert torch.get_num_threads() == learner
        venv.step(np.zeros((2, 5), dtype=np.float32))  # and the env steps on
        assert seen == [1, 1, 1, 1]
    finally:
        venv.close()
        torch.set_num_threads(before)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_a_bad_learner_threads_is_named_before_any_env_starts(bad):
    with pytest.raises(ValueError, match=f"learner_threads must be an int >= 1, got {bad!r}"):
        make_sb3_vec_env(ENV, 2, "state", backend="cpu", learner_threads=bad)


def test_ppo_runs_from_the_camera_on_cpu_workers():
    torch.manual_seed(0)
    venv = make_sb3_vec_env(ENV, 2, "rgbd", backend="cpu", seed=0)
    try:
        assert isinstance(venv, IRB120SB3VecEnv) and venv.render_mode is None
        model = PPO("MultiInputPolicy", venv, n_steps=64, batch_size=64, n_epochs=2, seed=0)
        assert isinstance(model.policy.features_extractor.extractors["image"], NatureCNN)
        before = [p.detach().clone() for p in model.policy.parameters()]
        model.learn(256)
        assert model.num_timesteps == 256
        assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))
        action, _ = model.predict(venv.reset(), deterministic=True)
        assert action.shape == (2, 5) and np.all(np.abs(action) <= 1)
    finally:
        venv.close()


def test_sac_runs_from_state_with_the_reward_and_control_mode_passed_through():
    venv = make_sb3_vec_env(ENV, 2, "state", backend="cpu", seed=0, reward_mode="sparse")
    try:
        assert venv.get_attr("reward_mode") == ["sparse", "sparse"]
        assert venv.get_attr("control_mode") == ["pd_ee_delta_tool"] * 2
        model = SAC("MlpPolicy", venv, learning_starts=100, batch_size=64, buffer_size=1000, seed=0)
        model.learn(300)
        assert model.replay_buffer.size() == 150  # per env: 300 steps of 2 envs
        assert model.logger.name_to_value  # SAC trained and logged its losses
        rewards = model.replay_buffer.rewards[:150]
        assert set(np.unique(rewards)) <= {0.0, 1.0}  # the sparse reward reached the learner
    finally:
        venv.close()


def test_a_partial_reset_reaches_sb3_as_a_new_episode_with_its_final_observation():
    """Env 1 restarted two steps in (a partial reset), so env 0 alone hits the 5-step limit; SB3 must see env 0's
    true last observation (the one a lone env with the same seed and actions reaches) as ``terminal_observation``,
    its next episode's first observation in the batch, a truncation, and Monitor's episode statistics."""
    hold = np.array([0, 0, 0, 0, 1], dtype=np.float32)
    venv = make_sb3_vec_env(ENV, 2, "rgbd", backend="cpu", seed=7, env_kwargs={"max_episode_steps": 5})
    ref = make_sb3_env(ENV, "rgbd", env_kwargs={"max_episode_steps": 5})
    try:
        venv.reset()
        ref_obs, _ = ref.reset(seed=7)  # env 0 of the vector env is seeded 7
        for t in range(5):
            if t == 2:
                venv.vector_env.reset(options={"env_idx": [1]})
            obs, rew, dones, infos = venv.step(np.stack([hold, hold]))
            ref_obs, ref_rew, term, trunc, _ = ref.step(hold)
            assert rew[0] == pytest.approx(ref_rew)
            if t < 4:
                assert not dones.any() and infos == [{}, {}]
        assert dones.tolist() == [True, False] and trunc and not term
        last = infos[0]["terminal_observation"]
        assert set(last) == {"image", "state"}
        assert np.array_equal(last["image"], ref_obs["image"]) and np.allclose(last["state"], ref_obs["state"])
        assert infos[0]["TimeLimit.truncated"] is True and infos[0]["is_success"] is False
        assert infos[0]["episode"]["l"] == 5 and isinstance(infos[0]["episode"]["r"], float)
        assert infos[1] == {}
        next_obs, _ = ref.reset()  # the lone env's next episode: the same seed sequence as env 0's auto-reset
        assert np.array_equal(obs["image"][0], next_obs["image"])
        assert not np.array_equal(obs["image"][0], last["image"])
    finally:
        venv.close()
        ref.close()


def test_the_maniskill_vector_env_path_of_the_gpu_runs_on_one_cpu_env():
    """``backend="auto"`` with one env and no CUDA is ManiSkill's own ``ManiSkillVectorEnv`` on physx_cpu: the class
    the GPU backend uses, so the adapter's GPU code path (its batched auto-reset, final_info, attributes) runs here."""
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    if torch.cuda.is_available():
        pytest.skip("with CUDA, backend='auto' is the GPU env itself (tests/gpu/)")
    venv = make_sb3_vec_env(ENV, 1, "rgbd", backend="auto", seed=3, env_kwargs={"max_episode_steps": 4})
    try:
        assert isinstance(venv.vector_env, ManiSkillVectorEnv)
        assert venv.get_attr("control_mode") == ["pd_ee_delta_tool"]
        obs = venv.reset()
        assert obs["image"].shape == (1, 4, 84, 84) and obs["image"].dtype == np.uint8
        hold = np.array([[0, 0, 0, 0, 1]], dtype=np.float32)
        for _ in range(4):
            obs, rew, dones, infos = venv.step(hold)
        assert dones.tolist() == [True] and infos[0]["TimeLimit.truncated"] is True
        assert infos[0]["episode"]["l"] == 4 and infos[0]["is_success"] is False
        assert not np.array_equal(infos[0]["terminal_observation"]["image"], obs["image"][0])  # the reset's is new
        model = PPO("MultiInputPolicy", venv, n_steps=16, batch_size=16, n_epochs=1, seed=0)
        model.learn(32)
        assert model.num_timesteps == 32 and len(model.ep_info_buffer) >= 4  # 4-step episodes, Monitor-style stats
    finally:
        venv.close()
