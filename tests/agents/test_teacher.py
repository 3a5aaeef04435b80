"""Teacher–student: a trained state policy labels the states in place of the scripted expert
(``agents.dagger --teacher``), reading the privileged state observation while the learner reads the camera."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401
from agents.common import make_envs
from agents.common.envs import privileged_state_obs
from maniskill_irb120.action import tcp_rotation, world_to_tool
from maniskill_irb120.experts import expert_for
from maniskill_irb120.policies import acting, read_policy_section

ENV = "GraspLift-IRB120-v1"
SHORT = dict(max_episode_steps=10)  # the tiny runs' episodes: labelling and training need no 150-step one


@pytest.mark.parametrize("env_id", ["TableClearing-IRB120-v1", ENV, "StackCube-IRB120-v1"])
def test_the_privileged_state_is_the_state_observation(env_id):
    """From the camera env, bit for bit what obs_mode="state" gives on the same seed and actions."""
    cam = gym.make(env_id, obs_mode="rgbd")
    ref = gym.make(env_id, obs_mode="state", render_backend="none")
    _, info = cam.reset(seed=4)
    obs, _ = ref.reset(seed=4)
    expert = expert_for(ref, reactive=True)
    expert.reset(None)
    for t in range(30):
        if t % 10 == 0:
            assert torch.equal(privileged_state_obs(cam, {**cam.unwrapped.get_info(), **info}), obs), t
        a = expert.act()
        _, _, _, _, info = cam.step(a)
        obs, *_ = ref.step(a)
    assert torch.equal(privileged_state_obs(cam, info), obs)
    cam.close()
    ref.close()


@pytest.fixture(scope="module")
def teacher(tmp_path_factory, tiny_dagger):
    """A state policy in the world frame (a tiny agents.dagger run: any trained state policy will do)."""
    out = tiny_dagger(
        tmp_path_factory.mktemp("teacher"), env_id=ENV, obs="state", action_frame="world", env_kwargs=SHORT
    )
    return out["checkpoint"]


def test_labels_are_the_teachers_actions_in_the_learners_frame(teacher):
    section = read_policy_section(teacher)
    act = acting(section)
    envs = make_envs(ENV, "rgbd", 1, backend="cpu", action_frame="tool", teacher=teacher)
    ref = gym.make(ENV, obs_mode="state", render_backend="none")
    try:
        _, info = envs.reset(seed=9)
        obs, _ = ref.reset(seed=9)
        g = torch.Generator().manual_seed(0)
        for _ in range(5):
            with torch.no_grad():
                want = world_to_tool(act({"state": obs}).clamp(-1, 1), tcp_rotation(ref.unwrapped.tcp_pose))
            torch.testing.assert_close(info["expert_action"], want, atol=1e-6, rtol=0)
            a = torch.rand(1, 5, generator=g) * 2 - 1
            _, _, _, _, info = envs.step(a)
            obs, *_ = ref.step(a)
    finally:
        envs.close()
        ref.close()


@pytest.fixture(scope="module")
def student(tmp_path_factory, tiny_dagger, teacher):
    """A camera agents.dagger run labelled by the teacher, with the auxiliary targets (a tiny one): its result dict."""
    return tiny_dagger(
        tmp_path_factory.mktemp("student"), env_id=ENV, obs="rgbd", action_frame="tool", encoder="keypoints",
        teacher=teacher, env_kwargs=SHORT, aux_weight=1.0,
    )  # fmt: skip


def test_a_camera_student_trains_from_the_teacher(student):
    section = read_policy_section(student["checkpoint"])
    assert section["obs"] == "rgbd" and student["env_steps"] > 0 and student["dataset"] > 0
    assert 0.0 <= student["success_rate"] <= 1.0


def test_a_teacher_that_cannot_label_the_run_is_named(teacher, student, tmp_path):
    with pytest.raises(FileNotFoundError, match="--teacher"):
        make_envs(ENV, "rgbd", 1, backend="cpu", teacher=tmp_path / "missing.pt")
    with pytest.raises(ValueError, match=r"--teacher .*env_id='GraspLift-IRB120-v1'"):
        make_envs("TableClearing-IRB120-v1", "state", 1, backend="cpu", teacher=teacher)
    camera = student["checkpoint"]  # a camera policy (the module's student: training another takes half a minute)
    with pytest.raises(ValueError, match=r"--teacher .*obs='rgbd' \(needed: 'state'\)"):
        make_envs(ENV, "rgbd", 1, backend="cpu", teacher=camera)


def test_the_perception_probe_reads_the_students_aux_head_beside_its_actions(student, tmp_path, capsys, repo_script):
    """scripts/perception_probe.py: the action it recomputes from the features its auxiliary head reads is the one
    sim2real-eval's policy sends, the truth it scores against is the cube relative to the TCP, and the labels are
    the teacher's, on the same seeds with and without the shift."""
    import json

    import numpy as np

    out = tmp_path / "probe.json"
    argv = ["--checkpoint", str(student["checkpoint"]), "--shift", "color=0.25,texture=1", "--episodes", "2"]
    res = repo_script("perception_probe").cli([*argv, "--out", str(out)])
    assert res == json.loads(out.read_text())
    assert set(res["conditions"]) == {"none", "shifted"}
    for c in res["conditions"].values():
        assert c["episodes"] == len(c["ends"]) == 2
        assert sum(b["steps"] for k, b in c["bands"].items() if k.startswith("all")) > 0
    runs = np.load(out.with_suffix(".npz"))
    for name in ("none", "shifted"):
        np.testing.assert_allclose(runs[f"{name}_act"], runs[f"{name}_head_act"], atol=1e-5)
        np.testing.assert_allclose(
            runs[f"{name}_aux_err_mm"], runs[f"{name}_aux_pred"] - runs[f"{name}_aux_true"], atol=1e-3
        )
        assert np.abs(runs[f"{name}_aux_true"]).max() > 10  # mm: the cube is not at the TCP
    # the same seeds: the first state's truth is the same in both conditions (a shift moves no geometry)
    np.testing.assert_allclose(runs["none_aux_true"][0], runs["shifted_aux_true"][0], atol=1e-4)
    assert "| condition | band |" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, said",
    [
        (["--shift", "colr=0.2"], "--shift 'colr=0.2'"),
        (["--shift", "color=0.2", "--episodes", "0"], "--episodes 0: at least 1"),
        (["--shift", "color=0.2", "--seed", "-1"], "--seed -1: episode seeds are 0 or more"),
        (["--shift", "color=0.2", "--checkpoint", "{tmp}/missing.pt"], "missing.pt: no such file"),
        (["--shift", "color=0.2", "--checkpoint", "{teacher}"], "has no auxiliary head"),
    ],
)
def test_the_perception_probe_refuses_bad_input_in_one_line(
    argv, said, student, teacher, tmp_path, capsys, repo_script
):
    """Before any env starts; the teacher is a run without --aux-weight."""
    argv = ["--checkpoint", str(student["checkpoint"]), *argv]
    argv = [x.format(tmp=tmp_path, teacher=teacher) for x in argv]
    with pytest.raises(SystemExit) as e:
        repo_script("perception_probe").cli(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and said in err and len(err.strip().splitlines()) == 1, err
