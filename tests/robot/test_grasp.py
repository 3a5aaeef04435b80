"""A grasp in physics: close on a 20 mm cube, lift it, hold it."""

from __future__ import annotations

import numpy as np
import pytest


def test_gripper_grasps_lifts_and_holds_cube(bench):
    env = bench.make()
    agent, cube = env.unwrapped.agent, env.unwrapped.cube
    # descend along the approach axis until the TCP is 3 mm above the cube centre
    for _ in range(40):
        gap = agent.tcp_pose.p[0, 2].item() - (bench.CUBE_HALF + 0.003)
        if gap < 5e-4:
            break
        env.step(np.array([min(gap / 0.01, 1.0), 0, 0, 0, 1], dtype=np.float32))
    close = np.array([0, 0, 0, 0, -1], dtype=np.float32)
    for _ in range(6):
        env.step(close)
    assert agent.is_grasping(cube).item()
    for _ in range(10):  # lift 10 cm
        env.step(np.array([-1, 0, 0, 0, -1], dtype=np.float32))
    for _ in range(int(2.0 * env.unwrapped.control_freq)):  # hold 2 s
        env.step(close)
    z = cube.pose.p[0, 2].item()
    assert z == pytest.approx(bench.CUBE_HALF + 0.10, abs=0.012)
    assert agent.is_grasping(cube).item()
    assert 0.016 < agent.gripper_opening.item() < 0.021  # pads on the 20 mm cube (~1 mm contact penetration)
    assert agent.is_static().item()
