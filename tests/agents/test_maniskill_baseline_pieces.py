"""What ManiSkill's own examples/baselines/ppo (ppo.py, ppo_rgb.py) need from our env, checked on CPU.

Those scripts hard-code physx_cuda; here we exercise the same wrappers, in the same order, on one CPU env
reached the way they reach it: gym.make("maniskill_irb120:TableClearing-IRB120-v1", ...).
"""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import torch
from mani_skill.utils import gym_utils
from mani_skill.utils.wrappers.flatten import FlattenActionSpaceWrapper, FlattenRGBDObservationWrapper
from mani_skill.utils.wrappers.record import RecordEpisode
from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

ENV = "maniskill_irb120:TableClearing-IRB120-v1"


def test_ppo_rgb_wrapper_stack(tmp_path):
    env = gym.make(
        ENV,
        num_envs=1,
        obs_mode="rgbd",
        render_mode="rgb_array",
        sim_backend="physx_cpu",
        control_mode="pd_joint_delta_pos",
        reward_mode="normalized_dense",
    )
    assert gym_utils.find_max_episode_steps_value(env) == 250
    env = FlattenRGBDObservationWrapper(env, rgb=True, depth=False, state=True)
    if isinstance(env.action_space, gym.spaces.Dict):
        env = FlattenActionSpaceWrapper(env)
    assert isinstance(env.action_space, gym.spaces.Box) and env.action_space.shape[-1] == 7  # 6 joints + gripper
    env = RecordEpisode(env, output_dir=str(tmp_path), save_trajectory=False, max_steps_per_video=20, video_fps=20)
    venv = ManiSkillVectorEnv(env, 1, ignore_terminations=False, record_metrics=True)
    obs, _ = venv.reset(seed=0)
    assert obs["rgb"].shape == (1, 84, 84, 3) and obs["rgb"].dtype == torch.uint8
    assert obs["state"].ndim == 2
    rewards = []
    for _ in range(20):
        obs, rew, term, trunc, info = venv.step(torch.zeros(1, 7))
        rewards.append(float(rew[0]))
    assert all(0.0 <= r <= 1.0 for r in rewards)
    assert "episode" in info and "success_once" in info["episode"]
    venv.close()
    assert list(tmp_path.glob("*.mp4"))


def test_ppo_state_obs_and_partial_reset():
    env = gym.make(
        ENV,
        num_envs=1,
        obs_mode="state",
        sim_backend="physx_cpu",
        reward_mode="normalized_dense",
        control_mode="pd_ee_delta_tool",
    )
    venv = ManiSkillVectorEnv(env, 1, ignore_terminations=False, record_metrics=True)
    obs, _ = venv.reset(seed=1)
    assert obs.shape[0] == 1 and obs.dtype == torch.float32
    obs2, _ = venv.reset(options=dict(env_idx=torch.tensor([0])))
    assert torch.isfinite(obs2).all()
    venv.close()


def test_env_id_resolves_in_fresh_interpreter_like_a_third_party_script():
    code = (
        "import gymnasium as gym, mani_skill.envs\n"
        f"e = gym.make('{ENV}', num_envs=1, obs_mode='state', sim_backend='physx_cpu')\n"
        "o, _ = e.reset(seed=0); print(type(e.unwrapped).__name__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0 and "TableClearingIRB120Env" in out.stdout, out.stderr[-2000:]
