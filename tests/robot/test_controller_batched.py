"""The arm controllers (``robot/controllers.py``) in a batch, exercised on CPU tensors: a task reset resets the
controllers of only the envs being reset, and state round trips carry the controller targets."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.maniskill_compat import episode_reset

ENV = "TableClearing-IRB120-v1"


CONTROL_MODES = [
    "pd_ee_delta_tool",
    "pd_ee_target_delta_tool",
    "pd_joint_pos",
    "pd_joint_delta_pos",
    "pd_ee_delta_pose",
]


def controller_targets(agent) -> dict[str, torch.Tensor]:
    out = {}
    for uid, c in agent.controller.controllers.items():
        for name in ("_target_qpos", "_start_qpos", "_target_pose"):
            t = getattr(c, name, None)
            if isinstance(t, torch.Tensor):
                out[f"{uid}.{name}"] = t.clone()
            elif t is not None and hasattr(t, "raw_pose"):
                out[f"{uid}.{name}"] = t.raw_pose.clone()
    return out


@pytest.mark.parametrize("mode", CONTROL_MODES)
def test_controller_reset_leaves_envs_that_are_not_reset(mode):
    env = gym.make(ENV, obs_mode="state", control_mode=mode)
    env.reset(seed=0)
    u = env.unwrapped
    a = torch.full((1, u.action_space.shape[-1]), 0.5)
    b = -a
    if mode == "pd_joint_pos":
        a[:, :6] = u.agent.robot.get_qpos()[:, :6] + 0.05
        b[:, :6] = a[:, :6] + 0.05
    env.step(a)
    u.agent.set_action(b)  # targets ahead of the measured joints (no physics step yet)
    before = controller_targets(u.agent)
    arm = u.agent.controller.controllers["arm"]
    assert not torch.allclose(arm._target_qpos, u.agent.robot.get_qpos()[:, :6], atol=1e-4)
    with episode_reset(u.scene, torch.zeros(1, dtype=torch.bool)):  # a reset of other envs
        assert bool(u.scene._reset_mask.all())  # what ManiSkill's controllers would have used
        u.agent.controller.reset()
    for k, v in controller_targets(u.agent).items():
        torch.testing.assert_close(v, before[k], msg=f"{mode}: {k} was reset")
    u.agent.controller.reset()  # outside a task reset: all envs, as ManiSkill does on a mode switch
    qpos = u.agent.robot.get_qpos()
    torch.testing.assert_close(arm._target_qpos, qpos[:, :6])
    env.close()


def test_state_round_trip_restores_target_controller():
    env = gym.make(ENV, obs_mode="state", control_mode="pd_ee_target_delta_tool")
    env.reset(seed=1)
    u = env.unwrapped
    for _ in range(3):
        env.step(torch.tensor([[0.5, 0.5, -0.5, 0.5, 1.0]]))
    saved_dict, saved_flat = u.get_state_dict(), u.get_state()
    assert set(saved_dict["controller"]["arm"]) == {"target_pose", "target_qpos"}
    a = torch.tensor([[0.0, -1.0, 0.5, -1.0, 1.0]])
    obs_a, *_ = env.step(a)
    targets_a = controller_targets(u.agent)
    for restore in (lambda: u.set_state_dict(saved_dict), lambda: u.set_state(saved_flat)):
        for _ in range(2):  # move the targets away, then restore
            env.step(torch.tensor([[1.0, 1.0, 1.0, 1.0, -1.0]]))
        restore()
        ctrl = u.agent.get_controller_state()["arm"]
        torch.testing.assert_close(ctrl["target_qpos"], saved_dict["controller"]["arm"]["target_qpos"])
        torch.testing.assert_close(
            ctrl["target_pose"], saved_dict["controller"]["arm"]["target_pose"], atol=1e-6, rtol=0
        )
        obs_b, *_ = env.step(a)
        for k, v in controller_targets(u.agent).items():
            torch.testing.assert_close(v, targets_a[k], atol=1e-5, rtol=0)
        torch.testing.assert_close(obs_b, obs_a, atol=1e-3, rtol=0)
    env.close()
