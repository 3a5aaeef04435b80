"""A fourth task written entirely here, with its own attribute names, runs through every layer with no edit
outside this file: the task contract, the expert (``register_expert``), demo recording and ManiSkill's replay
tool, and the real side (``IRB120Sim2RealEnv`` on the controller emulator with a digital twin of the task).

What it shows: the layers read a task only through what the base class declares (``target_object``,
``privileged_state()``, ``step_state``, ``tcp_pose``, ``state_observations``), not through attribute names.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.registration import REGISTERED_ENVS, register_env

pytest.importorskip("serial")
pytest.importorskip("lark")

from maniskill_irb120.abb.emulator.controller import ControllerEmulator  # noqa: E402
from maniskill_irb120.envs.base import IRB120TableEnv, grasp_yaw_error  # noqa: E402
from maniskill_irb120.experts.demos import collect_demos  # noqa: E402
from maniskill_irb120.experts.pick_place import EXPERTS, PickPlaceExpert, expert_for, register_expert  # noqa: E402
from maniskill_irb120.sim2real.agent import IRB120RealAgent  # noqa: E402
from maniskill_irb120.sim2real.env import IRB120Sim2RealEnv  # noqa: E402
from maniskill_irb120.sim2real.twin import DigitalTwin  # noqa: E402

ENV_ID = "LiftBlock-IRB120-test"
LIFT = 0.06  # block centre above the source tray floor


class LiftBlockEnv(IRB120TableEnv):
    """Lift the block 6 cm while holding it. Its names are its own (``block``, ``_block_pose``, ``block_pose``)."""

    def _load_scene(self, options: dict):
        self.build_trays()
        self.block = self.target_object = self._build_object("block", [0.2, 0.6, 0.9, 1])
        self.build_background()
        self.watch_contacts([self.block])

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        u = self._episode_draws(env_idx, joint_noise=6, block_xy=2, block_yaw=1)
        self._reset_robot(env_idx, u["joint_noise"])
        self.block.set_pose(self._spawn_in_source_tray(u["block_xy"], u["block_yaw"]))

    def privileged_state(self) -> dict[str, torch.Tensor]:
        return dict(block_pose=self.block.pose.raw_pose)

    def evaluate(self) -> dict:
        state = self._read_step_state()
        self._block_pose = state["block_pose"]  # a private cache of the task's own: never read by other layers
        contacts = self.contacts.flags()
        grasped = self._grasped(contacts.finger_forces[0], state["tcp_pose"][:, 3:]) & ~contacts.object_hit[0]
        height = state["block_pose"][:, 2] - self.source_center[:, 2]
        return dict(**self._common_info(contacts.robot_hit, grasped), success=grasped & (height >= LIFT), height=height)

    def state_observations(self, state: dict, info: dict) -> dict[str, torch.Tensor]:
        block, tcp = state["block_pose"], state["tcp_pose"]
        return dict(
            block_pose=block.clone(),
            tcp_to_block_pos=block[:, :3] - tcp[:, :3],
            tcp_to_block_yaw=grasp_yaw_error(block, tcp)[:, None],
        )

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        reach = 1 - torch.tanh(
            5 * torch.linalg.norm(self.step_state["block_pose"][:, :3] - self.tcp_pose[:, :3], dim=1)
        )
        grasped = info["grasped"].float()
        reward = torch.where(info["grasped"], 1.0, reach) + grasped * (1 + 2 * (info["height"] / LIFT).clamp(0, 1))
        reward = torch.where(info["success"], self.MAX_STAGED_REWARD, reward)
        return torch.where(info["fail"], 0.0, reward)


if ENV_ID not in REGISTERED_ENVS:
    register_env(ENV_ID, max_episode_steps=80)(LiftBlockEnv)


class LiftBlockExpert(PickPlaceExpert):
    """Pick the target object and hold it at the carry height (no place)."""


@pytest.fixture(autouse=True, scope="module")
def registered_expert():
    """``register_expert`` for this module's tests only: the other tests run every task in ``EXPERTS``, and
    ManiSkill's replay of a test-only env needs this file on the path (see the demo test)."""
    register_expert(ENV_ID)(LiftBlockExpert)
    yield
    EXPERTS.pop(ENV_ID)


# --------------------------------------------------------------------------- the task contract
def test_contract_reset_step_rewards_and_bad_input():
    env = gym.make(ENV_ID, obs_mode="state_dict", control_mode="pd_ee_delta_tool", render_backend="none")
    try:
        obs, info = env.reset(seed=0)
        assert obs["extra"]["block_pose"].shape == (1, 7) and "tcp_to_block_yaw" in obs["extra"]
        torch.testing.assert_close(obs["extra"]["tcp_pose"], env.unwrapped.tcp_pose)
        obs2, _ = env.reset(seed=0)
        torch.testing.assert_close(obs2["extra"]["block_pose"], obs["extra"]["block_pose"])  # seeded start
        obs, reward, term, trunc, info = env.step([0.0, 0.0, 0.0, 0.0, 1.0])  # a list is an action too
        assert reward.shape == (1,) and 0.0 <= float(reward[0]) <= 1.0  # normalized_dense by default
        dense = env.unwrapped.compute_dense_reward(obs, None, info)
        torch.testing.assert_close(reward, dense / LiftBlockEnv.MAX_STAGED_REWARD)
        torch.testing.assert_close(env.unwrapped.compute_sparse_reward(obs, None, info), info["success"].float())
        with pytest.raises(TypeError, match="action must be"):
            env.step("up")
        with pytest.raises(ValueError, match="env_idx"):
            env.reset(options=dict(env_idx=[3]))
    finally:
        env.close()
    with pytest.raises(ValueError, match="reward_mode"):
        gym.make(ENV_ID, reward_mode="shaped")
    with pytest.raises(ValueError, match="obs_mode"):
        gym.make(ENV_ID, obs_mode="lidar")


def expert_episode(env, seed: int, policy_env=None, limit: int = 80) -> tuple[bool, int]:
    env.reset(seed=seed)
    expert = expert_for(policy_env or env)
    expert.reset()
    for steps in range(1, limit + 1):  # noqa: B007 (its value after the loop is the episode length)
        _, _, term, trunc, info = env.step(expert.act()[0])
        if bool(term[0]) or bool(trunc[0]):
            break
    return bool(info["success"][0]), steps


def test_the_registered_expert_lifts_the_block():
    env = gym.make(ENV_ID, obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    try:
        assert type(expert_for(env)) is LiftBlockExpert
        assert [expert_episode(env, seed)[0] for seed in (0, 1)] == [True, True]
    finally:
        env.close()


# --------------------------------------------------------------------------- demos and ManiSkill's replay tool
def test_demos_record_and_replay_in_a_fresh_interpreter(tmp_path):
    demos = collect_demos(episodes=2, seed=3, out_dir=tmp_path, env_id=ENV_ID)
    assert demos["episodes_recorded"] == 2
    # collect_demos names the env "maniskill_irb120:<id>"; a test-only env is registered by this file instead,
    # so the fresh interpreter imports this file (by module name, on its PYTHONPATH) to make it
    js = Path(demos["json"])
    meta = json.loads(js.read_text())
    assert meta["env_info"]["env_id"] == f"maniskill_irb120:{ENV_ID}"
    meta["env_info"]["env_id"] = f"{Path(__file__).stem}:{ENV_ID}"
    js.write_text(json.dumps(meta))
    path = [str(Path(__file__).parent), str(Path(__file__).parents[2])]
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mani_skill.trajectory.replay_trajectory",
            "--traj-path",
            demos["h5"],
            "--use-env-states",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": ":".join(path)},
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "2/2=100.00%" in out.stdout + out.stderr


# --------------------------------------------------------------------------- the real side on the emulator twin
def test_real_side_reads_the_twins_declared_state():
    emu = ControllerEmulator("tcp")
    url = emu.start()
    twin = DigitalTwin(ENV_ID, emu, obs_mode="state_dict")
    sim = gym.make(ENV_ID, obs_mode="state_dict", control_mode="pd_ee_delta_tool")
    agent = IRB120RealAgent(url, camera=twin.camera, finger_qpos=twin.finger_qpos)
    env = IRB120Sim2RealEnv(sim, agent, world=twin)
    try:
        real_obs, _ = env.reset(seed=1)
        expert = expert_for(twin.env)
        expert.reset()
        for _ in range(5):  # a few steps of the expert, read from the twin as an operator's perception would
            real_obs, _, _, _, info = env.step(expert.act()[0])
            twin_obs = twin.obs
            # the object's pose and what follows from it are the twin's; the TCP is the robot's FK (the twin's
            # drives track the robot's joints, so its TCP is a little behind)
            torch.testing.assert_close(real_obs["extra"]["block_pose"], twin_obs["extra"]["block_pose"])
            np.testing.assert_allclose(real_obs["extra"]["tcp_pose"], env.unwrapped.tcp_pose, atol=1e-6)
            extra = real_obs["extra"]
            torch.testing.assert_close(extra["tcp_to_block_pos"], extra["block_pose"][:, :3] - extra["tcp_pose"][:, :3])
            np.testing.assert_allclose(extra["tcp_pose"][:, :3], twin_obs["extra"]["tcp_pose"][:, :3], atol=0.01)
        # the task's private cache exists on the sim, but the real side refuses it by name instead of the sim's
        assert hasattr(sim.unwrapped, "_block_pose")
        with pytest.raises(AttributeError, match="_block_pose"):
            env.unwrapped._block_pose  # noqa: B018
        assert expert_episode(env, 2, policy_env=twin.env)[0]
    finally:
        env.close()
        twin.close()
        emu.stop()
    assert emu.error is None, emu.error


def test_state_obs_without_a_world_are_refused_naming_the_pose():
    emu = ControllerEmulator("tcp")
    url = emu.start()
    sim = gym.make(ENV_ID, obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    agent = IRB120RealAgent(url)
    try:
        with pytest.raises(RuntimeError, match="'block_pose' is privileged object state"):
            IRB120Sim2RealEnv(sim, agent, real_reset_function=lambda env, seed, options: env.sim_env.reset(seed=seed))
    finally:
        agent.stop()
        emu.stop()


# --------------------------------------------------------------------------- a camera policy from the reward alone
def test_from_the_reward_to_a_camera_policy_with_no_expert(tmp_path, monkeypatch):
    """docs/adding_a_task.md's path at toy size: PPO learns a state teacher from the task's reward, then DAgger distils
    it into a camera student (--teacher). The expert is unregistered first: nothing in the pipeline may use it."""
    from agents import dagger, ppo
    from maniskill_irb120.policies import read_policy_section

    monkeypatch.delitem(EXPERTS, ENV_ID)
    toy = dict(env_id=ENV_ID, budget_min=0.05, eval_episodes=1, runs_dir=tmp_path, progress=False, capture_video=False)
    toy["env_kwargs"] = dict(max_episode_steps=20)  # a quarter of the task's 80: each episode, labelled or scored
    teacher = ppo.main(
        ppo.Args(
            **toy, exp_name="teacher", obs="state", state_net="mlp", obs_norm=True, num_envs=1, num_steps=8,
            num_minibatches=2, total_env_steps=16, eval_freq=0,
        )
    )  # fmt: skip
    student = dagger.main(
        dagger.Args(
            **toy, exp_name="student", obs="rgbd", action_frame="tool", encoder="keypoints",
            teacher=Path(teacher["checkpoint"]), num_envs=1, expert_episodes=1, episodes_per_round=1,
            updates_per_round=5, batch_size=16,
        )
    )  # fmt: skip
    section = read_policy_section(Path(student["checkpoint"]))
    assert section["obs"] == "rgbd" and section["env_id"] == ENV_ID
    assert student["env_steps"] > 0 and 0.0 <= student["success_rate"] <= 1.0
