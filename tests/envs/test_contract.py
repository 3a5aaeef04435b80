"""The env contract (``envs/contract.py``) under bad input: clear errors naming the problem, nothing silently
ignored. Short, seeded runs only (the CPU vector env's side of the contract is in tests/test_vector.py)."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)

ENV = "TableClearing-IRB120-v1"


# --------------------------------------------------------------------------- actions of the single env
def test_list_and_tuple_actions_step_like_arrays():
    envs = [gym.make(ENV, obs_mode="state") for _ in range(3)]
    try:
        a = [0.0, 0.5, 0.0, 1.0, 1.0]
        outs = []
        for e, action in zip(envs, (a, tuple(a), np.array(a, dtype=np.float32))):
            e.reset(seed=0)
            outs.append(e.step(action))
        for out in outs[:2]:
            torch.testing.assert_close(out[0], outs[2][0])  # same observation as the array action
            torch.testing.assert_close(out[1], outs[2][1])
        outs = [e.step([[1, 0, 0, 0, 1]]) for e in envs]  # batched nested list of ints
        assert outs[0][0].shape == (1, envs[0].unwrapped.single_observation_space.shape[0])
    finally:
        for e in envs:
            e.close()


@pytest.mark.parametrize(
    "bad,err,match",
    [
        ("open", TypeError, "got str 'open'"),
        ([0, 0, 0, 0, "x"], TypeError, "dtype <U"),
        (object(), TypeError, "got object"),
        ([True, False, True, False, True], TypeError, "dtype bool"),
        ([[0.0] * 5, [0.0]], ValueError, "rectangular"),
        ([0.0, 0.0, 0.0], ValueError, "shape"),
        ([0.0, float("nan"), 0.0, 0.0, 1.0], ValueError, "NaN"),
    ],
)
def test_bad_single_env_actions_raise_clear_errors(bad, err, match):
    e = gym.make(ENV, obs_mode="state")
    try:
        e.reset(seed=0)
        with pytest.raises(err, match=match):
            e.step(bad)
        e.step([0.0, 0.0, 0.0, 0.0, 1.0])  # still usable
    finally:
        e.close()


# --------------------------------------------------------------------------- num_envs, env_idx, obs_mode
@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on machines without CUDA")
def test_batched_env_without_cuda_says_use_make_vec_env():
    with pytest.raises(
        ValueError, match=r"CUDA GPU.*physx_cuda.*make_vec_env\(env_id, num_envs, backend=\"cpu\"\)"
    ) as e:
        gym.make(ENV, num_envs=4, obs_mode="state")
    # the advice works in a script only under the guard: the workers import the script again
    assert 'if __name__ == "__main__":' in str(e.value)


def test_batched_env_on_cpu_backend_and_bad_num_envs():
    with pytest.raises(ValueError, match="make_vec_env"):
        gym.make(ENV, num_envs=2, obs_mode="state", sim_backend="physx_cpu")
    for bad in (0, -1, 1.5, "2"):
        with pytest.raises(ValueError, match=f"num_envs must be a positive integer, got {re.escape(repr(bad))}"):
            gym.make(ENV, num_envs=bad, obs_mode="state")


def test_reset_env_idx_checked():
    e = gym.make(ENV, obs_mode="state")
    try:
        e.reset(seed=0)
        with pytest.raises(ValueError, match=r"\[5\] out of range: valid env indices are 0\.\.0"):
            e.reset(options={"env_idx": [5]})
        with pytest.raises(ValueError, match="out of range"):
            e.reset(options={"env_idx": torch.tensor([-1])})
        with pytest.raises(ValueError, match="selects no env"):
            e.reset(options={"env_idx": []})
        with pytest.raises(TypeError, match="integer env indices"):
            e.reset(options={"env_idx": [0.0]})
        with pytest.raises(TypeError, match="integer env indices"):
            e.reset(options={"env_idx": "0"})
        with pytest.raises(TypeError, match="options must be a dict"):
            e.reset(options=[("env_idx", [0])])
        a, _ = e.reset(seed=3, options={"env_idx": [0]})  # lists, tensors and masks of the right kind work
        b, _ = e.reset(seed=3, options={"env_idx": torch.tensor([0])})
        c, _ = e.reset(seed=3, options={"env_idx": np.array([True])})
        torch.testing.assert_close(a, b)
        torch.testing.assert_close(a, c)
    finally:
        e.close()


def test_obs_mode_error_lists_every_valid_mode():
    from mani_skill.envs.utils.observations import parse_obs_mode_to_struct

    from maniskill_irb120.envs.table_clearing import TableClearingIRB120Env

    for bad in ("telepathy", "rgb+smell", "", 3):
        with pytest.raises(ValueError, match="use one of") as err:
            gym.make(ENV, obs_mode=bad)
    listed = re.search(r"use one of (\[.*?\])", str(err.value)).group(1)
    names = eval(listed)  # the message's list literal
    assert {"rgbd", "rgb", "depth", "state", "state_dict", "none", "sensor_data"} <= set(names)
    for name in names:
        parse_obs_mode_to_struct(name)  # every mode the message offers is one ManiSkill accepts
    assert names == list(TableClearingIRB120Env.NAMED_OBS_MODES)


# --------------------------------------------------------------------------- after close()
def test_single_env_after_close_raises_clear_error():
    e = gym.make(ENV, obs_mode="state", render_mode="rgb_array")
    e.reset(seed=0)
    e.close()
    for call in (lambda: e.step(np.zeros(5)), lambda: e.reset(seed=0), e.render):
        with pytest.raises(RuntimeError, match="the env is closed"):
            call()
    e.close()  # closing twice is fine


# --------------------------------------------------------------------------- render_mode="all"
def test_render_all_frames_fit_video_macro_blocks():
    """Overview (512x512) beside the 84x84 hand camera is 596 wide; padded to 608 so encoders do not rescale."""
    e = gym.make(ENV, obs_mode="rgbd", render_mode="all")
    try:
        e.reset(seed=0)
        img = e.render()
        assert tuple(img.shape) == (1, 512, 608, 3) and img.dtype == torch.uint8
        assert int(img[:, :, 596:].abs().sum()) == 0  # the padding is black ...
        assert float(img[:, :84, 512:596].float().std()) > 1.0  # ... and the hand camera is still there
    finally:
        e.close()
