"""The rewards, their terms and the events in ``info`` equal, to float32 rounding, what the envs computed when
``data/reward_trajectories.npz`` was written (``data/reward_trajectories.py``), on its recorded actions, for every task
and reward mode: a change meant to make a step faster cannot change what a learner sees. Not bit for bit: the same
code on another x86 VM's CPU differed from the recording by up to 1.2e-5 relative (the last bits of float32), so
RTOL is a few times that; any change to a reward's formula or to an event moves it far more."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

_spec = importlib.util.spec_from_file_location(
    "reward_trajectories", Path(__file__).parent / "data" / "reward_trajectories.py"
)
rt = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(rt)
EPISODES, REWARD_MODES, TASKS = rt.EPISODES, rt.REWARD_MODES, rt.TASKS
DATA = np.load(rt.OUT)
RTOL, ATOL = 5e-5, 1e-5
"""float32 rounding across CPUs: relative, and absolute near zero (an object at rest: its speed differed by 2.2e-6)"""


@pytest.mark.parametrize("reward_mode", REWARD_MODES)
@pytest.mark.parametrize("env_id", TASKS)
def test_rewards_terms_and_events_are_unchanged(env_id, reward_mode):
    env: gym.Env = rt.make_env(env_id, reward_mode)
    try:
        for actor, seed in EPISODES:
            key = f"{env_id}/{actor}/{seed}"
            want = {k.split("/")[-1]: DATA[k] for k in DATA.files if k.startswith(f"{key}/{reward_mode}/")}
            env.reset(seed=seed)
            got: dict[str, list] = {"reward": []}
            for a in DATA[f"{key}/actions"]:
                _, reward, _, _, info = env.step(torch.as_tensor(a)[None])
                got["reward"].append(float(reward.double()[0]))
                for k, v in rt.numeric_info(info).items():
                    got.setdefault(k, []).append(v)
            assert sorted(got) == sorted(want), f"{key}: info keys changed"
            for k, v in want.items():
                np.testing.assert_allclose(
                    np.asarray(got[k], dtype=np.float64), v, rtol=RTOL, atol=ATOL, err_msg=f"{key} {reward_mode} {k}"
                )
    finally:
        env.close()


def test_the_recorded_episodes_cover_the_events():
    """The trajectories exercise what they guard: a grasp and a success per task, and some negative term."""
    for env_id in TASKS:
        expert = f"{env_id}/expert/{EPISODES[0][1]}/normalized_dense"
        assert DATA[f"{expert}/grasped"].any() and DATA[f"{expert}/success"].any(), env_id
    dense = [DATA[k] for k in DATA.files if k.endswith("/dense/reward")]
    assert any((r < 0).any() for r in dense)
