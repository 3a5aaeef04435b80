"""WorldFrameToolAction: a world-axis translation command moves the TCP along that world axis whatever the
tool's yaw (in physics), the label map is its inverse, and bad input is refused with the env still usable.
DropObservationKeys: the state without joint speeds is the full state with those entries cut out."""

from __future__ import annotations

import math

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.action import tool_to_world, world_to_tool
from maniskill_irb120.wrappers import DropObservationKeys, WorldFrameToolAction

ENV = "TableClearing-IRB120-v1"


@pytest.fixture(scope="module")
def env():
    e = WorldFrameToolAction(gym.make(ENV, obs_mode="state", render_backend="none"))
    yield e
    e.close()


def test_maps_are_inverse_for_a_yawed_tool():
    yaw = torch.tensor(0.6)
    # a tool pointing down (approach axis x = -z world), turned by ``yaw`` about the vertical
    c, s = math.cos(yaw), math.sin(yaw)
    rot = torch.tensor([[[0.0, -s, c], [0.0, c, s], [-1.0, 0.0, 0.0]]])
    world = torch.tensor([[0.3, -0.5, 0.2, 0.4, -1.0]])
    tool = world_to_tool(world, rot)
    assert torch.allclose(tool[:, 3:], world[:, 3:])  # yaw and gripper pass through
    assert not torch.allclose(tool[:, :3], world[:, :3])
    assert torch.allclose(tool_to_world(tool, rot), world, atol=1e-6)
    big = world_to_tool(torch.tensor([[1.0, 1.0, 0.0, 0.0, 1.0]]), rot)
    assert big[:, :3].abs().max() == pytest.approx(1.0)  # shrunk back into the box, direction kept
    assert big[0, 1] / big[0, 2] == pytest.approx((-s + c) / (c + s), rel=1e-5)


def test_world_x_command_moves_the_tcp_along_world_x_after_a_yaw(env):
    env.reset(seed=3)
    agent = env.unwrapped.agent
    for _ in range(4):  # turn the tool ~40 degrees about the vertical first
        env.step(torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0]))
    p0 = agent.tcp_pose.p[0].clone()
    for _ in range(5):
        env.step(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0]))
    d = agent.tcp_pose.p[0] - p0
    assert d[0] > 0.03, d  # ~1 cm per step along +x
    assert d[1].abs() < 0.2 * d[0] and d[2].abs() < 0.2 * d[0], d


@pytest.mark.parametrize(
    "bad, match",
    [(torch.zeros(4), "shape"), (torch.tensor([float("nan"), 0, 0, 0, 1.0]), "NaN")],
)
def test_bad_actions_are_refused_and_the_env_goes_on(env, bad, match):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(bad)
    env.step(torch.tensor([0.0, 0.0, -0.5, 0.0, 1.0]))


def test_needs_the_tool_control_mode():
    e = gym.make(ENV, obs_mode="state", render_backend="none", control_mode="pd_joint_pos")
    try:
        with pytest.raises(ValueError, match="pd_ee_delta_tool"):
            WorldFrameToolAction(e)
    finally:
        e.close()


def test_state_without_qvel_is_the_state_with_those_entries_cut_out():
    full = gym.make(ENV, obs_mode="state", render_backend="none")
    lean = DropObservationKeys(gym.make(ENV, obs_mode="state_dict", render_backend="none"), ["agent/qvel"])
    a, _ = full.reset(seed=1)
    b, _ = lean.reset(seed=1)
    step = torch.tensor([[1.0, 0.0, 0.0, 0.0, 1.0]])
    a2, b2 = full.step(step)[0], lean.step(step)[0]
    qvel = slice(8, 16)  # after the 8 joint angles (6 arm, 2 fingers)
    assert a2[0, qvel].abs().max() > 0  # there was something to cut
    for x, y in ((a, b), (a2, b2)):
        assert torch.equal(torch.cat([x[:, : qvel.start], x[:, qvel.stop :]], dim=1), y)
    assert lean.observation_space.shape == (1, 37) and lean.unwrapped.single_observation_space.shape == (37,)
    full.close()
    lean.close()


def test_drop_keys_names_a_missing_key_and_a_wrong_obs_mode():
    with pytest.raises(ValueError, match="agent has .*qvel"):
        DropObservationKeys(gym.make(ENV, obs_mode="state_dict", render_backend="none"), ["agent/qacc"])
    with pytest.raises(ValueError, match="'state_dict' or 'rgbd'"):
        DropObservationKeys(gym.make(ENV, obs_mode="state", render_backend="none"), ["agent/qvel"])
