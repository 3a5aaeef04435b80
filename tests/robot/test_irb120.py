"""The IRB 120 agent (``robot/irb120.py``): non-finite action rows held without a host sync (the GPU branch, on CPU
tensors), the hand camera's shader choice, and the README's "Use the robot alone" snippet."""

from __future__ import annotations

from types import SimpleNamespace

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.robot.irb120 import hand_camera_shader
from maniskill_irb120.robot.shaders import FORWARD

ENV = "TableClearing-IRB120-v1"


def test_nonfinite_rows_are_held_without_a_sync():
    """The CUDA branch of ``set_action`` (run here on CPU tensors): bad rows become the hold action."""
    env = gym.make(ENV, obs_mode="state")
    env.reset(seed=0)
    u = env.unwrapped
    env.step(torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0]]))  # gripper open
    held, bad = u.agent.hold_nonfinite(torch.tensor([[float("nan"), 0.2, 0.3, 0.4, -1.0]]))
    assert bool(bad[0]) and torch.equal(held, torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0]]))
    ok, bad = u.agent.hold_nonfinite(torch.tensor([[0.1, 0.2, 0.3, 0.4, -1.0]]))
    assert not bool(bad[0]) and torch.equal(ok, torch.tensor([[0.1, 0.2, 0.3, 0.4, -1.0]]))
    with pytest.raises(ValueError, match="NaN or inf"):  # the CPU keeps the synchronous error
        env.step(torch.tensor([[float("inf"), 0, 0, 0, 1.0]]))
    *_, info = env.step(torch.tensor([[0.0, 0, 0, 0, 1.0]]))
    assert not bool(info["invalid_action"][0])
    env.close()

    env = gym.make(ENV, obs_mode="state", control_mode="pd_joint_pos")
    env.reset(seed=0)
    u = env.unwrapped
    q = u.agent.controller.controllers["arm"]._target_qpos.clone()
    held, _ = u.agent.hold_nonfinite(torch.full((1, 7), float("nan")))
    torch.testing.assert_close(held[:, :6], q)  # absolute joint mode holds the current joint targets
    env.close()


def test_hand_camera_uses_minimal_on_a_gpu_renderer():
    gpu, cpu = SimpleNamespace(is_cuda=lambda: True), SimpleNamespace(is_cuda=lambda: False)
    assert hand_camera_shader(FORWARD, gpu) == "minimal"
    assert hand_camera_shader(FORWARD, cpu) == FORWARD
    assert hand_camera_shader("rt", gpu) == "rt"  # an explicit choice is kept


def test_readme_robot_alone_snippet_runs(readme_snippet):
    """The README's "Use the robot alone" snippet, as written (ManiSkill's Empty-v1 with our agent)."""
    ns: dict = {}
    exec(compile(readme_snippet("robot-alone"), "README.md:robot-alone", "exec"), ns)
    try:
        assert tuple(ns["obs"]["sensor_data"]["hand_camera"]["rgb"].shape) == (1, 84, 84, 3)
    finally:
        ns["env"].close()
