"""Each library's success statistic is the env's own: a scripted expert (and a still arm, which fails) runs through
the SB3 and skrl adapters on the CPU worker vector env, with its same-step auto-reset, and what SB3 keeps in
``ep_success_buffer`` (what it logs as ``rollout/success_rate``) and what skrl's trainer tracks as
``Episode / Success rate (mean)`` must match the success the env itself reported on each episode's last step.

Env 0 steps in this process (``CPUVectorEnv.local_first``), so the expert can read its state, and a recorder sits
between the vector env and it: the truth comes from the env's own step, not from any adapter's bookkeeping. Env 1, in
its worker, holds still and runs into the step limit, a failure."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from maniskill_irb120.experts import expert_for  # noqa: E402

ENV = "GraspLift-IRB120-v1"
LIMIT = 120  # steps an episode: the expert lifts the cube well within it, a still arm never does
PLAN = ("expert", "still", "expert")  # env 0's episodes: successes around a failure


class EpisodeEnds(gym.Wrapper):
    """Records the env's own ``success`` on the last step of every episode, before the vector env resets it."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.ends: list[bool] = []

    def step(self, action):
        obs, rew, term, trunc, info = self.env.step(action)
        if term or trunc:
            self.ends.append(bool(info["success"]))
        return obs, rew, term, trunc, info


def drive(vector_env, step, to_actions):
    """Steps the adapter (``step(actions) -> dones, out``) until env 0 ended ``len(PLAN)`` episodes; env 0 follows
    PLAN, env 1 holds still. Returns the env's own episode ends (env 0's, in order) and each step's adapter output."""
    recorder = EpisodeEnds(vector_env._local)
    vector_env._local = recorder
    expert = expert_for(recorder)
    expert.reset()
    still = np.zeros(vector_env.single_action_space.shape, dtype=np.float32)
    outputs = []
    while len(recorder.ends) < len(PLAN):
        mode = PLAN[len(recorder.ends)]
        a0 = expert.act()[0].cpu().numpy() if mode == "expert" else still
        actions = to_actions(np.stack([a0, still]))
        dones, out = step(actions)
        outputs.append((dones, out))
        if dones[0]:
            expert.reset()
    return recorder.ends, outputs


def test_sb3_success_buffer_is_the_envs_own_success(tmp_path):
    from stable_baselines3 import PPO

    from maniskill_irb120.integrations.sb3 import make_sb3_vec_env

    venv = make_sb3_vec_env(ENV, 2, "state", backend="cpu", seed=3, env_kwargs={"max_episode_steps": LIMIT})
    try:
        model = PPO("MlpPolicy", venv, n_steps=8, batch_size=16, seed=0)
        model._setup_learn(10_000)  # as learn() starts: SB3's episode buffers, and the first reset

        def step(actions):
            obs, rew, dones, infos = venv.step(actions)
            model._update_info_buffer(infos, dones)  # what SB3's rollout collectors call on every step
            return dones, infos

        truth, outputs = drive(venv.vector_env, step, lambda a: a)
        env0 = [infos[0]["is_success"] for dones, infos in outputs if dones[0]]
        env1 = [infos[1]["is_success"] for dones, infos in outputs if dones[1]]
        assert truth == [True, False, True], truth  # the expert succeeded, the still arm did not
        assert env0 == truth and env1 == [False] * len(env1) and env1
        # SB3's buffer in its own order (env index within a step): exactly the episodes that ended
        expected = [infos[i]["is_success"] for dones, infos in outputs for i in np.flatnonzero(dones)]
        assert list(model.ep_success_buffer) == expected and sorted(expected) == sorted(truth + env1)
        assert np.mean(model.ep_success_buffer) == pytest.approx(2 / (3 + len(env1)))  # rollout/success_rate
    finally:
        venv.close()


def test_skrl_logs_the_envs_own_success():
    pytest.importorskip("skrl")
    from maniskill_irb120.integrations.skrl import SUCCESS_KEY, make_skrl_env

    env = make_skrl_env(ENV, 2, "state", backend="cpu", seed=3, env_kwargs={"max_episode_steps": LIMIT})
    try:
        env.reset()

        def step(actions):
            _, _, term, trunc, info = env.step(actions)
            dones = (term | trunc).flatten().cpu().numpy()
            return dones, {k: v for k, v in info["episode"].items()}

        truth, outputs = drive(env._env, step, lambda a: torch.as_tensor(a))
        assert truth == [True, False, True], truth
        tracked = [out[SUCCESS_KEY].item() for dones, out in outputs if dones.any()]
        assert all(SUCCESS_KEY not in out for dones, out in outputs if not dones.any())  # nothing between episodes
        # env 1 (still) never succeeds: a step's rate is env 0's success when it ended there, halved beside env 1's end
        ends = iter(truth)
        want = [(next(ends) if d[0] else 0.0) / int(d.sum()) for d, _ in outputs if d.any()]
        assert tracked == pytest.approx(want) and max(tracked) > 0
        ends = iter(truth)
        episodes = [next(ends) if i == 0 else False for d, _ in outputs for i in np.flatnonzero(d)]
        assert list(env.recent_success) == episodes  # the wrapper's per-episode record, what a progress line reads
    finally:
        env.close()
