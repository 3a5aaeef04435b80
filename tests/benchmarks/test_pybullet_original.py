"""Quick checks of the PyBullet re-implementation of the original report's action loop
(benchmarks/lib/pybullet_loop.py)."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest

pb = pytest.importorskip("pybullet")

seed_mod = importlib.import_module("benchmarks.lib.pybullet_loop")


@pytest.fixture(scope="module")
def env():
    e = seed_mod.SeedPyBulletEnv(render=True, realtime=False, seed=0)
    yield e
    e.close()


def test_scene_has_all_bodies(env):
    c = env.cid
    assert pb.getNumBodies(physicsClientId=c) == 6
    assert set(env.bodies) == {"plane", "table", "source_tray", "dest_tray", "cube", "robot"}
    assert len(set(env.bodies.values())) == 6
    types = [
        pb.getJointInfo(env.robot, j, physicsClientId=c)[2]
        for j in range(pb.getNumJoints(env.robot, physicsClientId=c))
    ]
    assert types.count(pb.JOINT_REVOLUTE) == 6
    assert types.count(pb.JOINT_PRISMATIC) == 2
    # the cube rests in the source tray after the reset's settling
    obj = env.state()["obj_pos"]
    assert np.linalg.norm(obj[:2] - np.asarray(seed_mod.SOURCE_TRAY_XY)) < 0.1
    assert env.table_top < obj[2] < env.table_top + 0.05
    # start pose: TCP 0.25 m above the table, approach axis (TCP x) pointing down
    pos, orn = env.tcp_pose()
    assert np.allclose(pos, [0.0, seed_mod.SOURCE_TRAY_XY[1], env.table_top + seed_mod.START_HEIGHT], atol=1e-3)
    assert env._approach(orn)[2] == pytest.approx(-1.0, abs=1e-3)


def test_tool_x_action_moves_tcp_along_approach(env):
    env.reset()
    pos0, orn0 = env.tcp_pose()
    approach = env._approach(orn0)
    s = env.act(np.array([1.0, 0.0, 0.0, 0.0, 1.0]))
    assert s["converged"] and not s["collided"] and not s["skipped"]
    assert 0 < s["n_substeps"] < seed_mod.TIMEOUT_STEPS
    d = s["tcp_pos"] - np.asarray(pos0)
    assert np.dot(d, approach) == pytest.approx(0.01, abs=0.002)
    assert np.linalg.norm(d - np.dot(d, approach) * approach) < 0.002


def test_rotation_action_turns_about_approach(env):
    env.reset()
    _, orn0 = env.tcp_pose()
    s = env.act(np.array([0.0, 0.0, 0.0, 1.0, 1.0]))
    assert s["converged"]
    r0 = np.asarray(pb.getMatrixFromQuaternion(orn0)).reshape(3, 3)
    r1 = np.asarray(pb.getMatrixFromQuaternion(s["tcp_orn"])).reshape(3, 3)
    rel = r0.T @ r1  # rotation in the tool frame: about x by +10 deg
    assert rel[0, 0] == pytest.approx(1.0, abs=1e-3)
    assert math.degrees(math.atan2(rel[2, 1], rel[1, 1])) == pytest.approx(10.0, abs=0.5)


def test_rgbd_capture(env):
    s = env.act(np.zeros(5))
    assert s["rgb"].shape == (84, 84, 3) and s["rgb"].dtype == np.uint8
    assert s["depth"].shape == (84, 84) and np.issubdtype(s["depth"].dtype, np.floating)
    assert np.all(s["depth"] > 0) and np.all(s["depth"] <= seed_mod.CAM_FAR + 1e-3)
    assert s["rgb"].std() > 1.0  # not a blank image


def test_no_render_has_no_images():
    e = seed_mod.SeedPyBulletEnv(render=False, realtime=False, seed=1)
    try:
        s = e.act(np.array([0.0, 0.0, 0.5, 0.0, -1.0]))
        assert "rgb" not in s and "depth" not in s
        assert s["n_substeps"] > 0
    finally:
        e.close()


def test_quick_measure_stats():
    r = seed_mod.measure("render", 5, seed=0)
    assert r["n"] == 5 and len(r["times"]) == 5 and len(r["substeps"]) == 5
    keys = ["min", "25%", "50%", "75%", "max"]
    vals = [r[k] for k in keys]
    assert all(v > 0 for v in vals) and vals == sorted(vals)
    assert r["min"] <= r["mean"] <= r["max"] and r["std"] >= 0
    assert r["actions_per_s"] == pytest.approx(1.0 / r["mean"], rel=1e-6)
    assert r["mean_substeps"] > 0
    with pytest.raises(ValueError):
        seed_mod.measure("bogus", 1)
    assert "| render |" in seed_mod.markdown_table([r])
