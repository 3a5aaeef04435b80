"""skrl on the tasks through maniskill_irb120.integrations.skrl: its PPO trains from state and from the camera on the
CPU workers, success reaches skrl's logger, and a partial reset reaches skrl as a new episode with the ended episode's
final observation (skrl has no env checker of its own)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("skrl")

from skrl.agents.torch.ppo import PPO, PPO_CFG  # noqa: E402
from skrl.memories.torch import RandomMemory  # noqa: E402
from skrl.trainers.torch import SequentialTrainer  # noqa: E402
from skrl.utils.spaces.torch import flatten_tensorized_space, tensorize_space, unflatten_tensorized_space  # noqa: E402

from maniskill_irb120.integrations.sb3 import make_sb3_env  # noqa: E402
from maniskill_irb120.integrations.skrl import SUCCESS_KEY, make_skrl_env, policy_and_value  # noqa: E402

ENV = "GraspLift-IRB120-v1"


@pytest.mark.parametrize("obs", ["state", "rgbd"])
def test_skrl_ppo_trains_on_cpu_workers(obs, tmp_path):
    torch.manual_seed(0)
    env = make_skrl_env(ENV, 2, obs, backend="cpu", seed=0, env_kwargs={"max_episode_steps": 20})
    try:
        flat, _ = env.reset()
        assert flat.shape == (2, env.observation_space.shape[0] if obs == "state" else 4 * 84 * 84 + 25)
        cfg = PPO_CFG(rollouts=16, mini_batches=2, learning_epochs=2, time_limit_bootstrap=True)
        cfg.experiment.directory, cfg.experiment.write_interval = str(tmp_path), 16
        models = policy_and_value(env)
        before = [p.detach().clone() for p in models["policy"].parameters()]
        memory = RandomMemory(memory_size=cfg.rollouts, num_envs=env.num_envs, device=env.device)
        agent = PPO(
            models=models,
            memory=memory,
            observation_space=env.observation_space,
            action_space=env.action_space,
            device=env.device,
            cfg=cfg,
        )
        trainer = SequentialTrainer(
            env=env,
            agents=agent,
            cfg={"timesteps": 48, "headless": True, "disable_progressbar": True, "close_environment_at_exit": False},
        )
        trainer.train()
        assert any(not torch.equal(a, b) for a, b in zip(before, models["policy"].parameters()))  # 3 updates
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        (events,) = tmp_path.rglob("events.out.tfevents.*")
        acc = EventAccumulator(str(events))
        acc.Reload()
        tags = acc.Tags()["scalars"]
        # 48 steps of 20-step episodes: episodes ended, and skrl's log has their success and length (skrl's own
        # statistic, from our flags)
        assert SUCCESS_KEY in tags and "Episode / Total timesteps (mean)" in tags
        assert [e.value for e in acc.Scalars("Episode / Total timesteps (mean)")][-1] == 20
    finally:
        env.close()


def test_a_partial_reset_reaches_skrl_as_a_new_episode_with_its_final_observation():
    """As the SB3 test: env 1 restarted two steps in, env 0 alone hits the 5-step limit. skrl must get the
    truncation, env 0's next episode's first observation (one reset, not a second one on top of the vector env's
    auto-reset) and, in info, its true last observation; env 1 runs on."""
    hold = torch.tensor([[0, 0, 0, 0, 1]] * 2, dtype=torch.float32)
    env = make_skrl_env(ENV, 2, "rgbd", backend="cpu", seed=7, env_kwargs={"max_episode_steps": 5})
    ref = make_sb3_env(ENV, "rgbd", env_kwargs={"max_episode_steps": 5})
    flat = lambda o: flatten_tensorized_space(tensorize_space(env.observation_space, o))[0]  # noqa: E731
    try:
        env.reset()
        ref.reset(seed=7)
        for t in range(5):
            if t == 2:
                env._env.reset(options={"env_idx": [1]})
            obs, rew, term, trunc, info = env.step(hold)
            ref_obs, ref_rew, *_ = ref.step(hold[0].numpy())
            assert rew.shape == (2, 1) and rew[0, 0].item() == pytest.approx(ref_rew)
            if t < 4:
                assert not (term | trunc).any() and info["episode"] == {}
        assert trunc[:, 0].tolist() == [True, False] and not term.any()
        assert torch.equal(info["final_observation"][0], flat(ref_obs))
        assert info["episode"][SUCCESS_KEY].item() == 0.0 and info["episode"][SUCCESS_KEY].numel() == 1
        next_obs, _ = ref.reset()
        assert torch.equal(obs[0], flat(next_obs))
        image = unflatten_tensorized_space(env.observation_space, obs)["image"]
        assert image.shape == (2, 4, 84, 84) and image.max() <= 255 and np.isclose(float(image.min()), image.min())
    finally:
        env.close()
        ref.close()


def test_one_torch_thread_while_the_envs_step_and_the_learners_between_steps():
    """As the SB3 test: env 0 steps in this process beside the workers on one thread, skrl's learner gets
    ``learner_threads`` back after each step and reset."""
    before, seen = torch.get_num_threads(), []
    env = make_skrl_env(ENV, 2, "state", backend="cpu", seed=0, learner_threads=3)
    try:
        step, reset = env._env.step, env._env.reset
        env._env.step = lambda a: (seen.append(torch.get_num_threads()), step(a))[1]
        env._env.reset = lambda **kw: (seen.append(torch.get_num_threads()), reset(**kw))[1]
        assert torch.get_num_threads() == 3
        env.reset()
        env.step(torch.zeros(2, 5))
        assert seen == [1, 1] and torch.get_num_threads() == 3
    finally:
        env.close()
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match="learner_threads must be an int >= 1, got 0"):
        make_skrl_env(ENV, 2, "state", backend="cpu", learner_threads=0)


def test_the_maniskill_vector_env_path_of_the_gpu_runs_on_one_cpu_env():
    """``backend="auto"`` with one env and no CUDA is ManiSkill's own ``ManiSkillVectorEnv`` (the GPU backend's
    class) on physx_cpu: the adapter's spaces, device and auto-reset handling run on it here."""
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    if torch.cuda.is_available():
        pytest.skip("with CUDA, backend='auto' is the GPU env itself (tests/gpu/)")
    env = make_skrl_env(ENV, 1, "state", backend="auto", seed=3, env_kwargs={"max_episode_steps": 3})
    try:
        assert isinstance(env._env, ManiSkillVectorEnv) and env.num_envs == 1 and env.device.type == "cpu"
        obs, _ = env.reset()
        hold = torch.tensor([[0, 0, 0, 0, 1]], dtype=torch.float32)
        for _ in range(3):
            obs, rew, term, trunc, info = env.step(hold)
        assert trunc.tolist() == [[True]] and SUCCESS_KEY in info["episode"]
        assert info["final_observation"].shape == obs.shape and not torch.equal(info["final_observation"], obs)
    finally:
        env.close()


def test_the_policy_scores_its_own_sample_and_the_wrapper_clips_what_reaches_the_env():
    """skrl's ``clip_actions`` would score the clipped action: with the mean far outside [-1, 1] its log-probability
    falls thousands below zero and PPO's ratio overflows to NaN weights (as in the state GraspLift skrl PPO
    cell). The policy keeps its sample and its sample's log-probability; the wrapper steps the env with the
    action clipped to the bounds, as a reference env stepped with the bounds; a NaN is still refused, and the env
    steps on after it."""
    torch.manual_seed(0)
    env = make_skrl_env(ENV, 1, "state", backend="cpu", seed=7)
    ref = make_skrl_env(ENV, 1, "state", backend="cpu", seed=7)
    try:
        obs, _ = env.reset()
        ref.reset()
        policy = policy_and_value(env)["policy"]
        with torch.no_grad():
            policy.mean.weight.zero_()
            policy.mean.bias.fill_(50.0)
        actions, out = policy.act({"observations": obs}, role="policy")
        assert actions.min() > 40  # the sample itself, unclipped
        assert out["log_prob"].min() > -30  # its own: -5 * 0.92 - |z|^2 / 2, not -5 * 49^2 / 2
        obs, rew, *_ = env.step(actions)
        ref_obs, ref_rew, *_ = ref.step(torch.ones_like(actions))
        assert torch.equal(obs, ref_obs) and torch.equal(rew, ref_rew)
        with pytest.raises(ValueError, match="NaN or inf"):
            env.step(torch.full_like(actions, float("nan")))
        obs, rew, *_ = env.step(-actions)
        ref_obs, ref_rew, *_ = ref.step(-torch.ones_like(actions))
        assert torch.equal(obs, ref_obs) and torch.equal(rew, ref_rew)
    finally:
        env.close()
        ref.close()


def test_off_policy_agents_are_told_from_on_policy_ones_by_skrls_own_configs():
    """The benchmark keeps a replay memory beside ``agent.pt`` only for an off-policy agent, told by skrl's own
    config classes: SAC's and TD3's have a learning start, PPO's a rollout and none. An on-policy agent has no
    off-policy state to keep."""
    from types import SimpleNamespace

    from skrl.agents.torch.sac import SAC_CFG
    from skrl.agents.torch.td3 import TD3_CFG

    from maniskill_irb120.integrations.skrl import is_off_policy, off_policy_state

    assert is_off_policy(SimpleNamespace(cfg=SAC_CFG())) and is_off_policy(SimpleNamespace(cfg=TD3_CFG()))
    ppo = SimpleNamespace(cfg=PPO_CFG())
    assert not is_off_policy(ppo) and off_policy_state(ppo) == {}
