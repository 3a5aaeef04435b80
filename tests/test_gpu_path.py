"""The GPU path's mechanisms, exercised on the CPU (no GPU here): per-env episode randomness in partial
resets, controller resets of only the envs being reset, state round trips with controller targets,
the batched contact-pair layout, non-finite actions handled without a host sync, sync-free quaternions.

ManiSkill's CPU sim has one env, so where a batch is needed the test drives ManiSkill's own functions
(``BaseEnv._set_main_rng`` / ``_set_episode_rng``) on a stand-in with a batch of 4 envs.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.geometry.rotation_conversions import matrix_to_quaternion as ms_matrix_to_quaternion
from mani_skill.utils.geometry.rotation_conversions import quaternion_to_matrix

import maniskill_irb120  # noqa: F401
from maniskill_irb120 import make_vec_env
from maniskill_irb120.envs.base import IRB120TableEnv
from maniskill_irb120.maniskill_compat import episode_reset
from maniskill_irb120.robot.irb120 import hand_camera_shader
from maniskill_irb120.robot.kinematics import matrix_to_quaternion
from maniskill_irb120.robot.shaders import FORWARD

ENV = "TableClearing-IRB120-v1"


def batch_of_envs(num_envs: int) -> SimpleNamespace:
    """What ManiSkill's RNG methods and our ``_episode_draws`` read, for a batch of envs."""
    return SimpleNamespace(
        num_envs=num_envs,
        device=torch.device("cpu"),
        _enhanced_determinism=True,
        _main_seed=None,
        _episode_seed=None,
        _batched_episode_rng=None,
        _batched_rng_backend="numpy:random_state",
    )


def ms_reset_rng(fake, seed, env_idx) -> torch.Tensor:
    """ManiSkill 3.0.1's RNG steps of ``BaseEnv.reset`` (no reconfiguration), then our per-env draws."""
    BaseEnv._set_main_rng(fake, seed)
    BaseEnv._set_episode_rng(fake, seed, env_idx)
    return IRB120TableEnv._episode_draws(fake, env_idx, 9)


def test_partial_resets_draw_a_new_start_for_each_env():
    fake = batch_of_envs(4)
    ms_reset_rng(fake, 0, torch.arange(4))
    idx = torch.tensor([1, 2, 3])  # env 0 keeps running
    first, second = ms_reset_rng(fake, None, idx), ms_reset_rng(fake, None, idx)
    assert first.shape == (3, 9)
    assert not torch.allclose(first, second)  # each auto-reset of an env draws anew
    assert len({tuple(r.tolist()) for r in torch.cat([first, second])}) == 6
    # the defect this replaces: ManiSkill seeds torch with env 0's episode seed before every reset
    with torch.random.fork_rng():
        torch.manual_seed(int(fake._episode_seed[0]))
        a = torch.rand(3, 9)
        torch.manual_seed(int(fake._episode_seed[0]))
        assert torch.equal(a, torch.rand(3, 9))


def test_batched_draws_equal_single_env_draws_with_the_same_seeds():
    """GPU env i with episode seed s_i starts where a CPU env reset with seed s_i starts."""
    fake = batch_of_envs(3)
    batched = ms_reset_rng(fake, [10, 11, 12], torch.arange(3))
    env = gym.make(ENV, obs_mode="state")
    u = env.unwrapped
    for i, s in enumerate((10, 11, 12)):
        env.reset(seed=s)
        span = 0.08 - u.spawn_margin
        expect_xy = (batched[i, 6:8] * 2 - 1) * span + torch.tensor([0.35, 0.13])
        torch.testing.assert_close(u.obj.pose.p[0, :2], expect_xy, atol=1e-5, rtol=0)
    env.close()


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


def test_contact_pairs_one_fixed_layout():
    env = gym.make(ENV, obs_mode="state")
    env.reset(seed=0)
    u = env.unwrapped
    pairs = u.contacts.pairs
    links = {a.name for a, b in pairs if b in u.scene_actors and a is not u.obj}
    assert "base_link" not in links and "tcp" not in links  # stands on the table / has no shape
    assert len(pairs) == len(links) * 4 + 4 + 2
    assert u.contacts.impulses().shape == (len(pairs), 1, 3)
    env.close()


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


def test_matrix_to_quaternion_matches_maniskill_without_masks():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(512, 4, generator=g)
    q = torch.cat([q, torch.tensor([[0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]])])  # 180° turns
    m = quaternion_to_matrix(q / q.norm(dim=1, keepdim=True))
    ours, ref = matrix_to_quaternion(m), ms_matrix_to_quaternion(m)
    ref = ref * torch.where(ref[:, :1] < 0, -1.0, 1.0)
    torch.testing.assert_close(quaternion_to_matrix(ours), m, atol=1e-5, rtol=0)
    same = torch.minimum((ours - ref).abs().amax(1), (ours + ref).abs().amax(1))  # q and -q: one rotation
    assert float(same.max()) < 1e-5


def test_hand_camera_uses_minimal_on_a_gpu_renderer():
    gpu, cpu = SimpleNamespace(is_cuda=lambda: True), SimpleNamespace(is_cuda=lambda: False)
    assert hand_camera_shader(FORWARD, gpu) == "minimal"
    assert hand_camera_shader(FORWARD, cpu) == FORWARD
    assert hand_camera_shader("rt", gpu) == "rt"  # an explicit choice is kept


def test_make_vec_env_sim_backend_keyword():
    envs = make_vec_env(ENV, 1, backend="inprocess", sim_backend="physx_cpu", obs_mode="state")
    envs.reset(seed=0)
    envs.close()
    with pytest.raises(ValueError, match="sim_backend='physx_cuda'"):
        make_vec_env(ENV, 1, backend="inprocess", sim_backend="physx_cuda")
    with pytest.raises(ValueError, match="runs physx_cuda"):
        make_vec_env(ENV, 4, backend="gpu", sim_backend="physx_cpu")


def test_batched_benchmark_loop_runs_with_auto_reset():
    import importlib.util
    import sys
    from pathlib import Path

    bench = Path(__file__).resolve().parents[1] / "benchmarks"
    sys.path.insert(0, str(bench))  # sim_speed imports its sibling pybullet_seed
    try:
        spec = importlib.util.spec_from_file_location("sim_speed", bench / "sim_speed.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules["sim_speed"] = mod  # dataclasses look their module up while the file executes
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(bench))
    r = mod.measure_batched(ENV, 1, steps=260, seed=0, backend="inprocess", obs_mode="state")
    assert r["env_steps_per_s"] > 0
    assert r["episodes_finished"] >= 1  # random actions collide or time out at 250 steps: auto-reset ran
    assert not math.isnan(r["env_steps_per_s"]) and np.isfinite(r["gpu_mem_used_gb"])
