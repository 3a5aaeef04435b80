"""The env contract under bad input: clear errors naming the problem, nothing silently ignored, and
long-lived objects (the CPU vector env) still usable after a rejected call. Short, seeded runs only."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.vector import make_vec_env

ENV = "TableClearing-IRB120-v1"


# --------------------------------------------------------------------------- CPU vector env
@pytest.fixture(scope="module")
def venv():
    env = make_vec_env(ENV, 2, backend="cpu", obs_mode="state", max_episode_steps=50)
    yield env
    env.close()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_vector_env_rejects_non_finite_action_and_stays_usable(venv, bad):
    venv.reset(seed=0)
    actions = torch.zeros(2, 5)
    actions[1, 2] = bad
    with pytest.raises(ValueError, match=r"NaN or inf for env index \[1\]"):
        venv.step(actions)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))  # the workers are alive
    assert obs.shape[0] == 2 and torch.isfinite(rew).all()


@pytest.mark.parametrize(
    "bad,err,match",
    [
        ("left", TypeError, "str"),
        ([["a"] * 5] * 2, TypeError, "dtype"),
        (np.zeros((2, 5), dtype=object), TypeError, "dtype object"),
        (np.zeros((2, 5), dtype=bool), TypeError, "dtype bool"),
        (torch.zeros(2, 5, dtype=torch.complex64), TypeError, "complex"),
        ({"action": 0}, TypeError, "dict"),
        ([[0.0] * 5, [0.0] * 4], ValueError, "rectangular"),
        (np.zeros((2, 4)), ValueError, "shape"),
    ],
)
def test_vector_env_rejects_wrong_types_and_stays_usable(venv, bad, err, match):
    venv.reset(seed=0)
    with pytest.raises(err, match=match):
        venv.step(bad)
    venv.step(np.zeros((2, 5), dtype=np.int64))  # integers are numbers; the workers are alive


# --------------------------------------------------------------------------- README snippets
README = Path(__file__).resolve().parents[1] / "README.md"


def readme_snippet(name: str) -> str:
    """The fenced python block right after the marker ``<!-- README snippet "name" ... -->`` in README.md,
    so the tests run the README itself."""
    m = re.search(rf'<!-- README snippet "{re.escape(name)}".*?-->\s*```python\n(.*?)```', README.read_text(), re.S)
    assert m, f"README.md has no snippet marked {name!r}"
    return m.group(1)


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


def test_readme_robot_alone_snippet_runs():
    """The README's "Use the robot alone" snippet, as written (ManiSkill's Empty-v1 with our agent)."""
    ns: dict = {}
    exec(compile(readme_snippet("robot-alone"), "README.md:robot-alone", "exec"), ns)
    try:
        assert tuple(ns["obs"]["sensor_data"]["hand_camera"]["rgb"].shape) == (1, 84, 84, 3)
    finally:
        ns["env"].close()


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
                tcp=u._tcp_pose.clone(),
                obj=u._obj_pose.clone(),
                grasped=info["grasped"].clone(),
                cur={k: v.clone() for k, v in u._cur.items()},
            )
            for _, v in _leaves(obs):
                v.fill_(True) if v.dtype == torch.bool else v.fill_(5)
            torch.testing.assert_close(u.source_center, kept["source"])
            torch.testing.assert_close(u.dest_center, kept["dest"])
            torch.testing.assert_close(u._tcp_pose, kept["tcp"])
            torch.testing.assert_close(u._obj_pose, kept["obj"])
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


# --------------------------------------------------------------------------- num_envs, env_idx, obs_mode
@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on machines without CUDA")
def test_batched_env_without_cuda_says_use_make_vec_env():
    with pytest.raises(ValueError, match=r"CUDA GPU.*physx_cuda.*make_vec_env\(env_id, num_envs, backend=\"cpu\"\)"):
        gym.make(ENV, num_envs=4, obs_mode="state")


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


def test_vector_env_reset_env_idx_checked_and_stays_usable(venv):
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"\[2\] out of range: valid env indices are 0\.\.1"):
        venv.reset(options={"env_idx": [2]})
    with pytest.raises(ValueError, match="repeats"):
        venv.reset(options={"env_idx": [1, 1]})
    obs, _ = venv.reset(options={"env_idx": torch.tensor([1])})
    assert obs.shape[0] == 2
    venv.step(torch.zeros(2, 5))


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


def test_vector_env_after_close_raises_clear_error():
    v = make_vec_env(ENV, 1, backend="cpu", obs_mode="state")
    v.reset(seed=0)
    v.close()
    for call in (lambda: v.step(torch.zeros(1, 5)), lambda: v.reset(seed=0), v.render):
        with pytest.raises(RuntimeError, match="the vector env is closed"):
            call()
    v.close()


def test_vector_env_after_a_worker_died_says_so():
    """An error inside a worker (here an unknown attribute through call()) makes gymnasium shut that worker down;
    later calls say so instead of failing with 'NoneType' object has no attribute 'send'."""
    v = make_vec_env(ENV, 1, backend="cpu", obs_mode="state")
    try:
        v.reset(seed=0)
        with pytest.raises(RuntimeError, match="render_mode is not set"):  # checked before dispatch: no harm
            v.render()
        v.step(torch.zeros(1, 5))
        with pytest.raises(AttributeError, match="no_such_method"):
            v.call("no_such_method")
        with pytest.raises(RuntimeError, match=r"worker\(s\) \[0\] of this vector env were shut down"):
            v.step(torch.zeros(1, 5))
    finally:
        v.close()


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


def test_readme_vec_env_snippet_runs_as_a_script(tmp_path):
    """The README's make_vec_env snippet saved as a script and run: the CPU workers re-import the main
    module (forkserver), which only works under the ``if __name__ == "__main__":`` guard."""
    script = tmp_path / "vec_env_snippet.py"
    script.write_text(readme_snippet("vec-env"))
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "(2, 84, 84, 3) (2,)" in out.stdout, out.stdout


# --------------------------------------------------------------------------- videos with ManiSkill's RecordEpisode
def test_record_episode_info_on_video_writes_a_video(tmp_path):
    """ManiSkill 3.0.1's RecordEpisode(info_on_video=True) calls float() on a (1,)-shaped reward array each step,
    a TypeError from numpy 2.4 on: pyproject pins numpy < 2.4."""
    pytest.importorskip("imageio_ffmpeg", reason="needs imageio[ffmpeg] (dev extras)")
    from mani_skill.utils.wrappers.record import RecordEpisode

    assert np.lib.NumpyVersion(np.__version__) < "2.4.0", (
        f"numpy {np.__version__} is installed but pyproject.toml pins numpy<2.4 (ManiSkill 3.0.1's RecordEpisode "
        "with info_on_video needs it): reinstall with pip install -e '.[dev]'"
    )
    e = gym.make(
        ENV, obs_mode="state", render_mode="rgb_array", human_render_camera_configs=dict(width=128, height=128)
    )
    e = RecordEpisode(
        e, output_dir=str(tmp_path), save_trajectory=False, save_video=True, info_on_video=True, video_fps=20
    )
    e.reset(seed=0)
    for _ in range(3):
        e.step(np.array([0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32))
    e.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert videos and videos[0].stat().st_size > 0
