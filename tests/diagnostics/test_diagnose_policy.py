"""``scripts/diagnose_policy.py`` on tiny untrained SB3 TD3 and SAC models (short episodes): the JSON has the
per-stage table, the critic against the realised return and the replay buffer's counts, and the training policy's
exploration is played on request; bad input is one line and exit status 2."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

ENV = "GraspLift-IRB120-v1"


class Spaces(gym.Env):
    """The task's spaces and nothing else: enough for SB3 to build and briefly fill a model."""

    def __init__(self, obs_dim: int):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (5,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample().clip(-1, 1), {}

    def step(self, action):
        return self.observation_space.sample().clip(-1, 1), 0.25, False, False, {}


@pytest.fixture(scope="module")
def tiny_td3(tmp_path_factory):
    return tiny_model(tmp_path_factory, "td3")


@pytest.fixture(scope="module")
def tiny_sac(tmp_path_factory):
    return tiny_model(tmp_path_factory, "sac")


def tiny_model(tmp_path_factory, algo: str):
    from stable_baselines3 import SAC, TD3
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    import maniskill_irb120  # noqa: F401

    env = gym.make(ENV, obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    obs_dim = env.unwrapped.single_observation_space.shape[-1]
    env.close()
    d = tmp_path_factory.mktemp(f"tiny_{algo}")
    venv = VecNormalize(DummyVecEnv([lambda: Spaces(obs_dim)]), norm_reward=False)
    model = dict(td3=TD3, sac=SAC)[algo](
        "MlpPolicy", venv, gamma=0.8, learning_starts=100, policy_kwargs=dict(net_arch=[8]), seed=0
    )
    model.learn(total_timesteps=6)
    model.save(d / "model.zip")
    model.save_replay_buffer(d / "replay.pkl")
    venv.save(str(d / "vecnormalize.pkl"))
    return d


def test_one_short_episode_writes_the_stage_table(tiny_td3, tmp_path, capsys, repo_script):
    out = tmp_path / "diagnosis.json"
    d = tiny_td3
    repo_script("diagnose_policy").cli(["--model", str(d / "model.zip"), "--vecnormalize", str(d / "vecnormalize.pkl"),
                       "--replay", str(d / "replay.pkl"), "--episodes", "1", "--max-steps", "25",
                       "--out", str(out)])  # fmt: skip
    r = json.loads(out.read_text())
    assert r["algo"] == "td3" and r["gamma"] == 0.8 and r["episodes"] == 1 and r["episode_len"] == 25
    assert [s["stage"] for s in r["stages"]] == ["reach", "grasped", "lifted", "holding", "success"]
    first = r["stages"][0]
    assert first["episodes_reaching"] == 1.0 and first["steps"] >= 1
    for key in ("arm_saturated", "gripper_saturated", "gripper_closed", "tool_speed", "q", "realised_return",
                "q_minus_return", "q_still_minus_q", "mean_action", "ik_unreachable", "object_speed"):  # fmt: skip
        assert first[key] is not None, key
    # Q against the return only on the steps a truncation leaves whole: the first 25 - 21 (gamma 0.8's horizon)
    assert r["horizon"] == 21 and first["q_minus_return"] == pytest.approx(first["q"] - first["realised_return"])
    assert set(r["per_episode"][0]["first_step"]) == {"grasped", "lifted", "holding", "success"}
    assert r["replay"]["transitions"] == 6 and r["replay"]["bonus"] == 0 and r["replay"]["by_stage"]["grasped"] == 6
    assert r["replay"]["lifted_still"] == 0 and r["replay"]["lifted_arm_saturated"] is None
    assert "reach" in capsys.readouterr().out


def test_exploration_noise_plays_the_training_policy_seeded_by_episode(tiny_td3, tiny_sac, tmp_path, repo_script):
    """--action-noise adds TD3's Gaussian to the deterministic action (clipped to the bounds), --stochastic samples
    SAC's own distribution; each draws from the episode's seed, so a rerun repeats its actions, and each changes
    them from the deterministic ones."""

    def play(d, *extra: str) -> tuple[np.ndarray, dict]:
        out = tmp_path / f"d{len(list(tmp_path.iterdir()))}.json"
        argv = ["--model", str(d / "model.zip"), "--vecnormalize", str(d / "vecnormalize.pkl"), "--episodes", "1",
                "--max-steps", "5", *extra, "--out", str(out)]  # fmt: skip
        r = repo_script("diagnose_policy").cli(argv)
        return np.asarray(r["stages"][0]["mean_action"]), r

    plain, r0 = play(tiny_td3)
    noisy, r1 = play(tiny_td3, "--action-noise", "0.5")
    again, _ = play(tiny_td3, "--action-noise", "0.5")
    assert r0["action_noise"] == 0.0 and r1["action_noise"] == 0.5 and not r1["stochastic"]
    assert np.array_equal(noisy, again) and not np.allclose(noisy, plain) and np.abs(noisy).max() <= 1.0
    assert r1["stages"][0]["tool_speed"] != r0["stages"][0]["tool_speed"]  # the env stepped the noisy actions
    mean, _ = play(tiny_sac)
    sampled, r2 = play(tiny_sac, "--stochastic")
    resampled, _ = play(tiny_sac, "--stochastic")
    assert r2["stochastic"] and r2["algo"] == "sac" and np.array_equal(sampled, resampled)
    assert not np.allclose(sampled, mean)


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--model", "{tmp}/missing.zip"], "--model {tmp}/missing.zip does not exist"),
        (["--model", "{model}", "--episodes", "0"], "--episodes 0: give a whole number >= 1"),
        (["--model", "{model}", "--env-id", "GraspLift-v1"], "unknown env id 'GraspLift-v1'"),
        (["--model", "{tmp}/notes.txt"], "is not an SB3 model.zip"),
        (["--model", "{model}", "--action-noise", "-0.1"], "--action-noise -0.1: give a standard deviation >= 0"),
        (["--model", "{model}", "--action-noise", "nan"], "--action-noise nan: give a standard deviation >= 0"),
        (["--model", "{model}", "--action-noise", "0.1", "--stochastic"], "give one way to explore, not both"),
        (["--model", "{model}", "--stochastic"], "--stochastic: td3's actor is deterministic; --action-noise plays"),
    ],
)
def test_bad_input_is_one_line_and_status_2(tiny_td3, tmp_path, capsys, argv, says, repo_script):
    (tmp_path / "notes.txt").write_text("not a zip")
    fill = dict(tmp=str(tmp_path), model=str(tiny_td3 / "model.zip"))
    with pytest.raises(SystemExit) as e:
        repo_script("diagnose_policy").cli([a.format(**fill) for a in argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1 and says.format(**fill) in err, err
