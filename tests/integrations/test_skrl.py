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


_NET = dict(network=[dict(name="net", input="OBSERVATIONS", layers=[8], activations="relu")], output="ACTIONS")
"""a one-hidden-layer network with a linear output, in skrl's instantiator form"""


def _gaussian(log_std: float, squashed: bool):
    """A 5-action policy from skrl's instantiator (a linear layer's mean, zeroed), squashed or as skrl's clipped
    Gaussian, its log std set to ``log_std``."""
    import gymnasium as gym
    from skrl.utils.model_instantiators.torch import gaussian_model

    from maniskill_irb120.integrations.skrl import squashed_gaussian_model

    spaces = dict(observation_space=gym.spaces.Box(-np.inf, np.inf, (3,)), action_space=gym.spaces.Box(-1, 1, (5,)))
    build = squashed_gaussian_model if squashed else gaussian_model
    policy = build(device="cpu", clip_actions=not squashed, max_log_std=2.0, **spaces, **_NET)
    policy.act({"observations": torch.zeros(1, 3)}, role="policy")  # skrl's layers are lazy: shaped by a first call
    with torch.no_grad():
        for p in policy.parameters():
            p.zero_()
        policy.log_std_parameter.fill_(log_std)
    return policy


def test_a_squashed_gaussian_scores_its_sample_by_the_change_of_variables():
    """SquashedGaussianMixin's sample lies in [-1, 1] and its log-probability is torch's own tanh-transformed
    Gaussian's, whether sampled or given as ``taken_actions``; its deterministic action is the mean's tanh."""
    torch.manual_seed(0)
    policy = _gaussian(-0.5, squashed=True)
    with torch.no_grad():
        policy.net_container[0].bias.fill_(1.0)
        policy.net_container[-1].weight.fill_(0.15)  # mean 1.2: tanh 0.83, the sample often near the bound
    obs = torch.randn(4096, 3)
    actions, out = policy.act({"observations": obs}, role="policy")
    assert actions.abs().max() <= 1.0 and actions.shape == (4096, 5) and out["log_prob"].shape == (4096, 1)
    mean, std = out["mean_actions"].atanh(), out["log_std"].exp()
    ref = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean, std), [torch.distributions.TanhTransform(cache_size=1)]
    )
    inside = actions.abs().amax(-1) < 0.999  # where the reference's atanh is still exact in float32
    assert inside.float().mean() > 0.5
    expected = ref.log_prob(actions.clamp(-0.999, 0.999)).sum(-1, keepdim=True)
    assert torch.allclose(out["log_prob"][inside], expected[inside], atol=2e-2)
    _, again = policy.act({"observations": obs, "taken_actions": actions}, role="policy")
    assert torch.allclose(again["log_prob"][inside], out["log_prob"][inside], atol=2e-2)
    assert torch.allclose(out["mean_actions"], torch.tanh(torch.full((4096, 5), 1.2)), atol=1e-4)


def test_a_clipped_gaussians_entropy_grows_with_its_std_and_a_squashed_ones_does_not():
    """Why SAC's policy is squashed: SAC buys entropy, and skrl's clipped Gaussian scores the clipped action by the
    Gaussian's density, so its entropy grows as σ does while its actions pile at the bounds; the skrl SAC screening
    cell's log std ran to its clamp, 2 (σ 7.4). A tanh-squashed Gaussian's entropy is highest near σ 1 and falls
    beyond, so its temperature holds σ."""
    torch.manual_seed(0)
    obs = torch.zeros(20000, 3)

    def entropy(log_std, squashed):
        _, out = _gaussian(log_std, squashed).act({"observations": obs}, role="policy")
        return -out["log_prob"].mean().item()

    clipped = [entropy(s, squashed=False) for s in (-1.0, 0.0, 2.0)]
    squashed = [entropy(s, squashed=True) for s in (-1.0, 0.0, 2.0)]
    assert clipped[0] < clipped[1] < clipped[2]
    assert squashed[2] < squashed[1] and squashed[2] < squashed[0]


def test_a_squashed_gaussian_refuses_what_it_cannot_mean():
    import gymnasium as gym

    from maniskill_irb120.integrations.skrl import squashed_gaussian_model

    obs = gym.spaces.Box(-np.inf, np.inf, (3,))
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        squashed_gaussian_model(observation_space=obs, action_space=gym.spaces.Box(-2, 2, (5,)), device="cpu", **_NET)
    box = gym.spaces.Box(-1, 1, (5,))
    with pytest.raises(ValueError, match="clip_actions"):
        squashed_gaussian_model(observation_space=obs, action_space=box, device="cpu", clip_actions=True, **_NET)
    with pytest.raises(ValueError, match="reduction 'mean'"):
        squashed_gaussian_model(observation_space=obs, action_space=box, device="cpu", reduction="mean", **_NET)
