"""TableClearing-IRB120-v1: reward terms, events, determinism, API checks and the scripted expert.

Real physics on ``physx_cpu`` with num_envs=1; every scenario is driven through env.step.
"""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch

import maniskill_irb120  # noqa: F401  (registers the env)
from maniskill_irb120.envs import scene as ts
from maniskill_irb120.envs import table_clearing as tc
from maniskill_irb120.envs.table_clearing import ENV_ID
from maniskill_irb120.experts.pick_place import CARRY, TableClearingExpert
from maniskill_irb120.experts.rollout import run_expert

TERMS = tc.REWARD_TERMS


def make(**kw):
    kw.setdefault("obs_mode", "state")
    kw.setdefault("reward_mode", "dense")  # the original report's terms (the default is normalized_dense)
    return gym.make(ENV_ID, **kw)


@pytest.fixture
def env():
    e = make()
    yield e
    e.close()


def step(env, action):
    obs, rew, term, trunc, info = env.step(torch.as_tensor(action, dtype=torch.float32).reshape(1, 5))
    return obs, rew, term, trunc, info


def expert_until(env, expert, cond, limit=200):
    """Step the expert until ``cond(info)``; returns that step's (reward, terminated, info)."""
    for _ in range(limit):
        _, rew, term, _, info = step(env, expert.act())
        if cond(info):
            return rew, term, info
        assert not bool(term[0]), f"episode ended early: {info}"
    raise AssertionError("condition never met")


def val(info, k) -> float:
    return float(info[k][0])


def expert_trace(env, seed: int, term_key: str, stop, limit: int = 250):
    """Reset to ``seed``, step the expert until ``stop(info, terminated)``; returns the expert, the values
    of ``term_key`` at every step and the last step's (reward, terminated, info)."""
    env.reset(seed=seed)
    expert = TableClearingExpert(env.unwrapped)
    expert.reset()
    values = []
    for _ in range(limit):
        _, rew, term, _, info = step(env, expert.act())
        values.append(val(info, term_key))
        if stop(info, term):
            break
    return expert, values, (rew, term, info)


def check_sum(rew, info):
    assert float(rew[0]) == pytest.approx(sum(val(info, k) for k in TERMS))


# --------------------------------------------------------------------------- reward terms
def test_time_term_every_step_and_reward_is_sum_of_terms(env):
    env.reset(seed=0)
    for a in ([0, 0, 0, 0, 1], [0.5, 0.3, -0.2, 0.5, -1], [-1, 0, 0, 0, 1]):
        _, rew, _, _, info = step(env, a)
        assert val(info, "r_time") == -1.0
        check_sum(rew, info)


def test_approach_plus_when_closer_minus_when_farther(env):
    env.reset(seed=1)
    u = env.unwrapped
    expert = TableClearingExpert(u)
    expert.reset()
    _, rew, _, _, info = step(env, expert.act())  # heads for the hover point above the object
    assert val(info, "r_approach") == 1.0
    check_sum(rew, info)
    _, _, _, _, info = step(env, [-1, 0, 0, 0, 1])  # backs off along the approach axis (up)
    assert val(info, "r_approach") == -1.0
    assert val(info, "r_carry") == 0.0  # nothing held


def test_collision_driving_into_the_table(env):
    env.reset(seed=0)
    for _ in range(60):
        _, rew, term, _, info = step(env, [1, 0, 0, 0, 1])  # straight down along the approach axis
        if bool(info["collided"][0]):
            break
        assert val(info, "r_collision") == 0.0
    assert bool(info["collided"][0]) and bool(info["fail"][0]) and bool(term[0])
    assert val(info, "r_collision") == -1000.0
    check_sum(rew, info)


def test_grasp_event_then_carry_terms(env):
    expert, seen_grasp, (rew, term, info) = expert_trace(env, 2, "r_grasp", lambda i, t: bool(i["grasped"][0]))
    assert seen_grasp[-1] == 100.0 and all(r == 0.0 for r in seen_grasp[:-1])
    check_sum(rew, info)
    # held: next step the grasp event does not repeat
    _, _, _, _, info = step(env, expert.act())
    assert bool(info["grasped"][0]) and val(info, "r_grasp") == 0.0
    # carry towards the destination tray: +1 ...
    rew, term, info = expert_until(env, expert, lambda i: int(expert.phase[0]) == CARRY and val(i, "r_carry") != 0)
    assert val(info, "r_carry") == 1.0 and val(info, "r_approach") == 0.0
    _, _, _, _, info = step(env, expert.act())
    assert val(info, "r_carry") == 1.0
    # ... and -1 moving away from it (world +y; the TCP's y axis is tilted by the yaw, so use the rotation)
    u = env.unwrapped
    rot = u.agent.tcp_pose.to_transformation_matrix()[0, :3, :3]
    local = rot.T @ torch.tensor([0.0, 1.0, 0.0])
    _, _, _, _, info = step(env, [*local.tolist(), 0, -1])
    assert bool(info["grasped"][0])
    assert val(info, "r_carry") == -1.0


def test_drop_when_opening_mid_carry(env):
    env.reset(seed=3)
    expert = TableClearingExpert(env.unwrapped)
    expert.reset()
    expert_until(env, expert, lambda i: int(expert.phase[0]) == CARRY and bool(i["grasped"][0]))
    for _ in range(10):
        _, rew, term, _, info = step(env, [0, 0, 0, 0, 1])  # open in mid air over the gap
        if bool(info["dropped"][0]):
            break
    assert bool(info["dropped"][0]) and val(info, "r_drop") == -200.0
    check_sum(rew, info)
    _, _, _, _, info = step(env, [0, 0, 0, 0, 1])
    assert val(info, "r_drop") == 0.0  # edge, not level


def test_delivery_success_and_terminated(env):
    def stop(info, term):
        assert val(info, "r_collision") == 0.0 and val(info, "r_drop") == 0.0
        return bool(term[0])

    _, deliveries, (rew, term, info) = expert_trace(env, 4, "r_delivery", stop)
    assert bool(info["success"][0]) and bool(info["delivered"][0]) and bool(term[0])
    assert deliveries[-1] == 200.0 and all(d == 0.0 for d in deliveries[:-1])
    check_sum(rew, info)


def test_sparse_and_normalized_dense_rewards():
    for mode in ("sparse", "normalized_dense"):
        e = make(reward_mode=mode)
        e.reset(seed=4)
        expert = TableClearingExpert(e.unwrapped)
        expert.reset()
        rewards = []
        for _ in range(250):
            _, rew, term, _, info = step(e, expert.act())
            rewards.append(float(rew[0]))
            if bool(term[0]):
                break
        assert bool(info["success"][0])
        assert all(0.0 <= r <= 1.0 for r in rewards)
        assert rewards[-1] == pytest.approx(1.0)
        if mode == "sparse":
            assert all(r == 0.0 for r in rewards[:-1])
        else:
            assert max(rewards[:-1]) < 1.0
        e.close()


def test_cpu_contact_pass_matches_pairwise_queries(env):
    """The CPU single-pass contact scan agrees with ManiSkill's pairwise queries (the GPU code path's
    pair layout) through a whole expert episode (finger and scene contacts) and a collision."""
    env.reset(seed=6)
    u = env.unwrapped
    expert = TableClearingExpert(u)
    expert.reset()
    seen = set()

    def both():
        fast, slow = u.contacts.scan(), u.contacts.pairwise()
        for f, s in zip(fast[:2], slow[:2]):
            assert torch.equal(f, s)
        torch.testing.assert_close(fast[2], slow[2], atol=1e-3, rtol=1e-4)  # finger forces, same sign convention
        return fast

    for _ in range(250):
        _, _, term, _, info = step(env, expert.act())
        robot_hit, obj_hit, forces = both()
        assert bool(u._grasped(forces[0], u.agent.tcp_pose.q)[0]) == bool(u.agent.is_grasping(u.obj)[0])
        seen.add((bool(robot_hit[0]), bool(obj_hit[0, 0]), bool(u._touches(forces[0])[0])))
        if bool(term[0]):
            break
    assert (False, False, True) in seen and (False, True, False) in seen  # held / resting
    env.reset(seed=6)
    for _ in range(60):
        _, _, term, _, info = step(env, [1, 0, 0, 0, 1])
        if bool(term[0]):
            break
    assert bool(both()[0][0])


# --------------------------------------------------------------------------- scene, resets, determinism
def test_trays_reachable_pointing_down(env):
    """Every tray corner, 1..15 cm above the floor, at several yaws, has an IK solution."""
    env.reset(seed=0)
    u = env.unwrapped
    ctrl = u.agent.arm_controller
    q0 = u.agent.robot.get_qpos()[:, :6]
    down = ctrl.ee_pose_at_base()[0, :3, :3]
    targets = []
    for (cx, cy), sx, sy, dz, yaw in itertools.product(
        (ts.SOURCE_TRAY_XY, ts.DEST_TRAY_XY),
        (-1, 1),
        (-1, 1),
        (0.01, 0.05, 0.10, 0.15),
        (0.0, math.pi / 4, -math.pi / 4),
    ):
        t = torch.eye(4)
        c, s = math.cos(yaw), math.sin(yaw)
        t[:3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ down
        t[:3, 3] = torch.tensor([cx + sx * ts.TRAY_INNER / 2, cy + sy * ts.TRAY_INNER / 2, ts.TRAY_FLOOR_TOP + dz])
        targets.append(t)
    targets = torch.stack(targets)
    q, ok = ctrl.ik.solve(targets, q0.repeat(len(targets), 1))  # closed form: one call
    assert ctrl.ik.method == "closed_form"
    assert bool(ok.all()), targets[~ok][:, :3, 3]
    reached = ctrl.chain.forward_kinematics(q)
    torch.testing.assert_close(reached, targets, atol=1e-4, rtol=0)
    q = q0.repeat(len(targets), 1)
    for _ in range(10):  # damped least squares does a few iterations per call; chain calls to converge
        q, ok = ctrl.ik.solve_dls(targets, q)
    assert bool(ok.all()), targets[~ok][:, :3, 3]


def test_object_spawn_inside_source_tray_and_seeded(env):
    poses = {}
    for seed in (0, 1, 0):
        env.reset(seed=seed)
        u = env.unwrapped
        p = u.obj.pose.raw_pose[0].clone()
        rel = p[:2] - torch.tensor(ts.SOURCE_TRAY_XY)
        assert bool((rel.abs() <= ts.TRAY_INNER / 2 - ts.SPAWN_MARGIN + 1e-6).all())
        assert float(p[2]) == pytest.approx(ts.TRAY_FLOOR_TOP + u.object_half_size, abs=1e-5)
        if seed in poses:
            assert torch.equal(poses[seed], p)
        poses[seed] = p
    assert not torch.allclose(poses[0], poses[1])


def test_expert_trajectory_deterministic():
    a = run_expert(ENV_ID, 2, seed=7, record=True)
    b = run_expert(ENV_ID, 2, seed=7, record=True)
    for ta, tb in zip(a["trajectories"], b["trajectories"]):
        assert torch.equal(ta["actions"], tb["actions"])
        assert torch.equal(ta["tcp"], tb["tcp"])
        assert ta["success"] and tb["success"]


def test_partial_reset_restores_seeded_state(env):
    env.reset(seed=5)
    u = env.unwrapped
    p0 = u.obj.pose.raw_pose.clone()
    tcp0 = u.agent.tcp_pose.p.clone()
    for _ in range(5):
        step(env, [1, 0.5, 0, 1, 1])
    _, info = env.reset(seed=5, options=dict(env_idx=torch.tensor([0])))
    assert torch.allclose(u.obj.pose.raw_pose, p0, atol=1e-6)
    assert torch.allclose(u.agent.tcp_pose.p, tcp0, atol=1e-4)
    _, _, _, _, info = step(env, [0, 0, 0, 0, 1])
    assert val(info, "r_grasp") == 0.0 and val(info, "r_delivery") == 0.0


# --------------------------------------------------------------------------- API
def test_gymnasium_env_checker():
    from gymnasium.utils.env_checker import check_env
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    e = CPUGymWrapper(make())
    # skip_close_check: that check rebuilds the env from ``env.spec``, which fails for every ManiSkill
    # env because ManiSkill's TimeLimitWrapper is not a gymnasium RecordConstructorArgs wrapper
    # ("TimeLimitWrapper wrapper does not inherit from RecordConstructorArgs"); close() is called below.
    check_env(e, skip_render_check=True, skip_close_check=True)
    e.close()


def test_defaults_and_module_prefixed_make_in_fresh_interpreter():
    code = (
        "import gymnasium as gym, sys\n"
        f"env = gym.make('maniskill_irb120:{ENV_ID}', obs_mode='state')\n"
        "u = env.unwrapped\n"
        "assert u.control_mode == 'pd_ee_delta_tool', u.control_mode\n"
        "assert u.reward_mode == 'normalized_dense', u.reward_mode\n"
        "assert u.single_action_space.shape == (5,), u.single_action_space.shape\n"
        "assert u.obs_mode == 'state'\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-2000:]


def test_render_ahead_gives_the_same_observations():
    """The frame started before evaluate() is the frame get_obs() would have taken: same images, every
    step and across resets, as with ManiSkill's own capture order."""
    envs = [gym.make(ENV_ID, obs_mode="rgbd", max_episode_steps=12) for _ in range(2)]
    envs[1].unwrapped.render_ahead = False
    obs = [e.reset(seed=4)[0] for e in envs]
    rng = np.random.default_rng(4)
    captured_ahead = 0
    orig = envs[0].unwrapped._get_obs_sensor_data

    def counting(*a, **k):
        nonlocal captured_ahead
        captured_ahead += bool(envs[0].unwrapped._captured_ahead)
        return orig(*a, **k)

    envs[0].unwrapped._get_obs_sensor_data = counting
    for step in range(30):
        a = rng.uniform(-1, 1, 5).astype(np.float32)
        out = [e.step(a) for e in envs]
        for k in ("rgb", "depth"):
            assert torch.equal(
                out[0][0]["sensor_data"]["hand_camera"][k], out[1][0]["sensor_data"]["hand_camera"][k]
            ), (step, k)
        if out[0][2] or out[0][3]:
            obs = [e.reset() for e in envs]
            assert torch.equal(
                obs[0][0]["sensor_data"]["hand_camera"]["rgb"], obs[1][0]["sensor_data"]["hand_camera"]["rgb"]
            )
    assert captured_ahead == 30  # every step's frame was started early
    for e in envs:
        e.close()


def test_rgbd_default_obs_mode_and_hand_camera_shapes():
    e = gym.make(ENV_ID)
    assert e.unwrapped.obs_mode == "rgbd"
    obs, _ = e.reset(seed=0)
    cam = obs["sensor_data"]["hand_camera"]
    assert cam["rgb"].shape == (1, 84, 84, 3) and cam["rgb"].dtype == torch.uint8
    assert cam["depth"].shape == (1, 84, 84, 1)
    assert set(obs["sensor_data"]) == {"hand_camera"}  # the policy's only camera, as in the seed
    assert float(cam["rgb"].float().std()) > 1.0  # something is rendered
    obs, *_ = e.step(torch.zeros(1, 5))
    assert obs["sensor_data"]["hand_camera"]["rgb"].shape == (1, 84, 84, 3)
    e.close()
    e = make(render_mode="rgb_array")
    e.reset(seed=0)
    assert tuple(e.render().shape) == (1, 512, 512, 3)
    e.close()


def test_state_obs_has_privileged_fields():
    e = make(obs_mode="state_dict")
    obs, _ = e.reset(seed=0)
    extra = obs["extra"]
    for k in ("tcp_pose", "is_grasped", "obj_pose", "source_tray_pos", "dest_tray_pos", "tcp_to_obj_pos"):
        assert k in extra, k
    assert "gripper_opening" in obs["agent"]
    e.close()


def test_grasp_yaw_observation_tracks_the_tool_turn():
    """tcp_to_obj_yaw is the turn that aligns the fingers with a cube face: turning the tool by a yaw action
    changes it by that much (modulo the cube's 90° symmetry), and it stays within ±45°."""
    e = make(obs_mode="state_dict")
    obs, _ = e.reset(seed=2)
    before = float(obs["extra"]["tcp_to_obj_yaw"][0, 0])
    assert abs(before) <= math.pi / 4
    obs, *_ = e.step(torch.tensor([[0.0, 0.0, 0.0, 0.5, 1.0]]))  # +5° about the approach axis
    turned = float(obs["extra"]["tcp_to_obj_yaw"][0, 0]) - before
    turned = (turned + math.pi / 4) % (math.pi / 2) - math.pi / 4
    assert abs(abs(turned) - math.radians(5)) < math.radians(1.0), math.degrees(turned)
    e.close()


@pytest.mark.parametrize(
    "kwargs,bad",
    [
        (dict(reward_mode="shiny"), "shiny"),
        (dict(obs_mode="telepathy"), "telepathy"),
        (dict(control_mode="pd_mind_control"), "pd_mind_control"),
        (dict(robot_uids="panda"), "panda"),
    ],
)
def test_bad_modes_raise_clear_errors(kwargs, bad):
    kwargs.setdefault("obs_mode", "state")
    with pytest.raises(ValueError, match=bad):
        gym.make(ENV_ID, **kwargs)


def test_bad_actions_raise(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(1, 4))
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.tensor([[0.0, np.nan, 0, 0, 1]]))


# --------------------------------------------------------------------------- expert
def test_expert_success_rate():
    res = run_expert(ENV_ID, 20, seed=1000)
    assert res["episodes"] == 20
    assert res["success_rate"] >= 0.9, res
    assert res["mean_steps"] < 0.6 * 250
