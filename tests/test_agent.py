"""The IRB 120 agent in real SAPIEN physics: kinematics vs ABB's data, the tool-frame controller,
a grasp, the hand camera, the description build and the doctor."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import gymnasium as gym
import mani_skill.envs  # noqa: F401
import numpy as np
import pytest
import sapien
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.building import actors
from mani_skill.utils.geometry.rotation_conversions import matrix_to_axis_angle
from mani_skill.utils.registration import REGISTERED_ENVS, register_env
from mani_skill.utils.scene_builder.table import TableSceneBuilder  # noqa: F401  (ManiSkill import check)
from mani_skill.utils.building.ground import build_ground

import maniskill_irb120  # noqa: F401
from maniskill_irb120.agents.irb120 import IRB120Metalwork
from maniskill_irb120 import robot_description as rd

REPO = Path(__file__).resolve().parents[1]
CUBE_HALF = 0.01


if "IRB120CubeBench-test" not in REGISTERED_ENVS:

    @register_env("IRB120CubeBench-test", max_episode_steps=1000)
    class CubeBench(BaseEnv):
        """Robot on the floor, a red 20 mm cube under the rest pose's TCP: the bare grasp scenario."""

        SUPPORTED_ROBOTS = ["irb120_metalwork"]
        SUPPORTED_REWARD_MODES = ["none"]

        def __init__(self, *args, robot_uids="irb120_metalwork", **kwargs):
            super().__init__(*args, robot_uids=robot_uids, **kwargs)

        def _load_agent(self, options: dict):
            super()._load_agent(options, sapien.Pose())

        def _load_scene(self, options: dict):
            self.ground = build_ground(self.scene)
            self.cube = actors.build_cube(self.scene, half_size=CUBE_HALF, color=[1, 0, 0, 1], name="cube",
                                          initial_pose=sapien.Pose(p=[0.35, 0, CUBE_HALF]))

        def _initialize_episode(self, env_idx, options):
            qpos = torch.as_tensor(self.agent.keyframes["rest"].qpos, dtype=torch.float32)
            self.agent.reset(qpos.expand(len(env_idx), -1))
            self.cube.set_pose(sapien.Pose(p=[0.35, 0, CUBE_HALF]))

        def evaluate(self):
            return {}

        def _get_obs_extra(self, info):
            return {}



def make(obs_mode="none", control_mode="pd_ee_delta_tool", **kw):
    env = gym.make("IRB120CubeBench-test", obs_mode=obs_mode, control_mode=control_mode, reward_mode="none", **kw)
    env.reset(seed=0)
    return env


OPEN = np.array([0, 0, 0, 0, 1], dtype=np.float32)


def tcp_matrix(env) -> torch.Tensor:
    return env.unwrapped.agent.tcp_pose.to_transformation_matrix()[0].double()


# ------------------------------------------------------------------ kinematics vs ABB
def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    m = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    t = np.eye(4)
    t[:3, :3] = m
    return t


def trans(x=0.0, z=0.0) -> np.ndarray:
    t = np.eye(4)
    t[0, 3], t[2, 3] = x, z
    return t


def abb_flange(q) -> np.ndarray:
    """ABB's published IRB 120 chain: 0.290 base-axis2, 0.270 axis2-3, 0.070 offset, 0.302 to wrist, 0.072 flange."""
    return (trans(z=0.290) @ rot("z", q[0]) @ rot("y", q[1]) @ trans(z=0.270) @ rot("y", q[2])
            @ trans(x=0.302, z=0.070) @ rot("x", q[3]) @ rot("y", q[4]) @ trans(x=0.072) @ rot("x", q[5]))


CONFIGS = [np.zeros(6), [0.5, 0.3, -0.2, 0.4, 0.6, 0.7], [-1.2, -0.8, 0.9, -1.5, 1.1, -2.0],
           [2.5, 1.2, -1.5, 2.0, -1.8, 5.0], [0.0, 0.33, 0.46, 0.0, 0.78, 0.0], [-2.8, -1.9, 1.2, 2.7, 2.0, -6.5]]


def test_flange_fk_matches_abb_chain():
    env = make()
    robot = env.unwrapped.agent.robot
    residuals = []
    for q in CONFIGS:
        robot.set_qpos(torch.tensor([list(q) + [0.0, 0.0]], dtype=torch.float32))
        sim = robot.links_map["link6"].pose.to_transformation_matrix()[0].double().numpy()
        ref = abb_flange(q)
        residuals.append(np.linalg.norm(sim[:3, 3] - ref[:3, 3]))
        assert np.allclose(sim[:3, :3], ref[:3, :3], atol=1e-4)
    # 0.6 mm: the seed's axis-3 offset is 0.0706 m where ABB quotes 0.070 m
    assert max(residuals) < 1e-3, residuals


def test_joint_limits_and_speeds_match_abb():
    env = make()
    lim = env.unwrapped.agent.robot.get_qlimits()[0].numpy()
    deg = np.degrees(lim[:6])
    np.testing.assert_allclose(deg, [[-165, 165], [-110, 110], [-110, 70], [-160, 160], [-120, 120], [-400, 400]],
                               atol=1e-3)
    np.testing.assert_allclose(lim[6:], [[0, 0.012], [0, 0.012]], atol=1e-7)
    import xml.etree.ElementTree as ET

    vel = {j.get("name"): float(j.find("limit").get("velocity"))
           for j in ET.parse(rd.urdf_path()).getroot().iter("joint") if j.find("limit") is not None}
    np.testing.assert_allclose(np.degrees([vel[f"joint_{i}"] for i in range(1, 7)]),
                               [250, 250, 250, 320, 320, 420], rtol=1e-6)


def test_own_kinematics_matches_pytorch_kinematics():
    import pytorch_kinematics as pk

    from maniskill_irb120.kinematics import SerialChain

    chain = SerialChain(rd.urdf_path(), "tcp")
    ref = pk.build_serial_chain_from_urdf(Path(rd.urdf_path()).read_bytes(), end_link_name="tcp")
    q = torch.as_tensor(np.array(CONFIGS), dtype=torch.float32)
    tip, jac = chain.fk_with_jacobian(q)
    jac_ref, tip_ref = ref.jacobian(q, ret_eef_pose=True)
    torch.testing.assert_close(tip, tip_ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(jac, jac_ref, atol=1e-5, rtol=0)


def test_closed_form_ik_inverts_fk_on_its_branch():
    from maniskill_irb120.kinematics import SerialChain, SphericalWristIK

    chain = SerialChain(rd.urdf_path(), "tcp", dtype=torch.float64)
    ik = SphericalWristIK(chain)
    gen = torch.Generator().manual_seed(0)
    q = chain.lower + (chain.upper - chain.lower) * torch.rand(2000, 6, generator=gen, dtype=torch.float64)
    target = chain.forward_kinematics(q)
    sol, ok = ik.solve(target, q)
    assert bool(ok.all())
    torch.testing.assert_close(chain.forward_kinematics(sol), target, atol=1e-9, rtol=0)
    # with q0 = q, away from the wrist singularity, the solution on q0's branch is q itself
    regular = torch.sin(q[:, 4]).abs() > 0.1
    torch.testing.assert_close(sol[regular], q[regular], atol=1e-6, rtol=0)
    # out of reach (1 m away): not ok, and q0 comes back unchanged
    far = target[:4].clone()
    far[:, 0, 3] += 1.0
    sol, ok = ik.solve(far, q[:4])
    assert not bool(ok.any()) and torch.equal(sol, q[:4])
    with pytest.raises(ValueError, match="6 revolute joints"):
        SphericalWristIK(SerialChain(rd.urdf_path(), "link4"))


def test_kinematics_numpy_and_torch_backends_agree():
    """CPU tensors run the math in numpy, CUDA tensors in torch: the same function, so both must agree."""
    from maniskill_irb120.kinematics import SerialChain, SphericalWristIK

    chain = SerialChain(rd.urdf_path(), "tcp")
    ik = SphericalWristIK(chain)
    gen = torch.Generator().manual_seed(1)
    q = chain.lower + (chain.upper - chain.lower) * torch.rand(64, 6, generator=gen)
    fk_np = chain.forward_kinematics(q)
    fk_torch = chain.fk(torch, chain.consts(torch, q), q)
    torch.testing.assert_close(fk_np, fk_torch, atol=1e-6, rtol=0)
    q0 = q + 0.01 * torch.randn(64, 6, generator=gen)
    sol_np, ok_np = ik.solve(fk_np, q0)
    sol_t, ok_t = ik._solve(torch, ik.consts(torch, q0), fk_np, q0)
    assert sol_np.dtype == sol_t.dtype == torch.float32 and torch.equal(ok_np, ok_t)
    torch.testing.assert_close(sol_np, sol_t, atol=1e-4, rtol=0)


def test_controller_step_numpy_and_torch_backends_agree():
    """The fused FK/delta/IK/speed-check pass: numpy (CPU sim) and torch (GPU sim) agree."""
    from maniskill_irb120.kinematics import ArmIK

    env = make()
    ctrl = env.unwrapped.agent.arm_controller
    ik = ctrl.ik
    gen = torch.Generator().manual_seed(2)
    q0 = ctrl.qpos.repeat(32, 1) + 0.3 * torch.randn(32, 6, generator=gen)
    action = (torch.rand(32, 4, generator=gen) * 2 - 1) * torch.tensor([0.01, 0.01, 0.01, math.radians(10)])
    action[0] = torch.tensor([0.0, 0.0, 0.0, 0.0])
    for ref in (None, ctrl.chain.forward_kinematics(q0)):
        q_np, ok_np, pose_np = ik.tool_step(q0, action, ref)
        q_t, ok_t, pose_t = ArmIK._closed_form_tool_step(torch, ik.consts(torch, q0), q0, action, ref)
        assert torch.equal(ok_np, ok_t) and bool(ok_np.float().mean() > 0.8)
        torch.testing.assert_close(q_np, q_t, atol=1e-4, rtol=0)
        torch.testing.assert_close(pose_np, pose_t, atol=1e-5, rtol=0)
        torch.testing.assert_close(q_np[0], q0[0], atol=1e-4, rtol=0)  # a zero action keeps the joints


def test_closed_form_ik_crosses_the_wrist_singularity_smoothly():
    """Through q5 = 0 the nearer wrist solution keeps q4 and q6 and lets q5 change sign, as DLS would,
    instead of flipping both by half a turn."""
    from maniskill_irb120.kinematics import SerialChain, SphericalWristIK

    chain = SerialChain(rd.urdf_path(), "tcp", dtype=torch.float64)
    ik = SphericalWristIK(chain)
    q0 = torch.tensor([[0.2, 0.3, 0.1, 0.4, 0.02, -0.3]], dtype=torch.float64)
    q_goal = q0.clone()
    q_goal[0, 4] = -0.02
    sol, ok = ik.solve(chain.forward_kinematics(q_goal), q0)
    assert bool(ok.all())
    torch.testing.assert_close(sol, q_goal, atol=1e-6, rtol=0)


def test_tool_step_needing_a_too_fast_joint_is_refused():
    """Wrist centre 2 mm in front of axis 1: a 6 mm step back across the axis needs axis 1 to turn half a
    turn in one 50 ms control period (ABB: 250 deg/s): refused and flagged, the arm keeps its target;
    a 1 mm step forward is fine."""
    from maniskill_irb120.kinematics import SphericalWristIK

    env = make()
    agent = env.unwrapped.agent
    ctrl = agent.arm_controller
    ik = SphericalWristIK(ctrl.chain)
    q = torch.zeros(1, 8)
    q[0, 2] = ik.phi - math.pi / 2  # forearm straight up: the wrist centre right above axis 2
    q[0, 4] = 0.5
    agent.robot.set_qpos(q)
    agent.controller.reset()
    tcp = ctrl.chain.forward_kinematics(q[:, :6])[0]
    wrist_x = float((tcp[:3, 3] + tcp[:3, :3] @ ik.w_tip)[0])
    # shift the whole arm so the wrist centre sits 2 mm in front of axis 1
    q[0, 2] -= 0.002 / ik.L + wrist_x / ik.L
    agent.robot.set_qpos(q)
    agent.controller.reset()
    before = ctrl._target_qpos.clone()
    for dx_m, refused in ((-0.006, True), (0.001, False)):
        tcp = ctrl.chain.forward_kinematics(agent.robot.get_qpos()[:, :6])[0]
        tool_step = tcp[:3, :3].T @ torch.tensor([dx_m, 0.0, 0.0])  # root-frame x step, in the tool frame
        agent.set_action(torch.cat([tool_step / 0.01, torch.zeros(1), torch.ones(1)])[None])
        assert bool(agent.ik_unreachable[0]) is refused
        if refused:
            torch.testing.assert_close(ctrl._target_qpos, before)
        else:
            assert float((ctrl._target_qpos - before).abs().max()) < 0.05


# ------------------------------------------------------------------ the tool-frame controller
@pytest.mark.parametrize("solver", ["closed_form", "dls"])
def test_tool_delta_moves_tcp_as_commanded(solver):
    env = make()
    if solver == "dls":  # what ik_solver="dls" (or a chain without a spherical wrist) gets
        env.unwrapped.agent.arm_controller.ik.method = "dls"
    rng = np.random.default_rng(0)
    for _ in range(8):
        a = np.r_[rng.uniform(-1, 1, 4), 1.0].astype(np.float32)
        t0 = tcp_matrix(env)
        env.step(a)
        for _ in range(5):
            env.step(OPEN)
        rel = torch.linalg.inv(t0) @ tcp_matrix(env)
        np.testing.assert_allclose(rel[:3, 3].numpy(), a[:3] * 0.01, atol=2e-3)
        aa = matrix_to_axis_angle(rel[:3, :3][None])[0].numpy()
        np.testing.assert_allclose(aa, [math.radians(10) * a[3], 0, 0], atol=math.radians(1.0))
        assert not env.unwrapped.agent.ik_unreachable.any()


def test_out_of_range_actions_are_clipped_to_limits():
    env = make()
    t0 = tcp_matrix(env)
    env.step(np.array([5.0, -7.0, 0, 3.0, 1], dtype=np.float32))  # clipped to [1, -1, 0, 1]
    for _ in range(5):
        env.step(OPEN)
    rel = torch.linalg.inv(t0) @ tcp_matrix(env)
    np.testing.assert_allclose(rel[:3, 3].numpy(), [0.01, -0.01, 0], atol=2e-3)
    assert matrix_to_axis_angle(rel[:3, :3][None])[0, 0].item() == pytest.approx(math.radians(10), abs=math.radians(1))


def test_unreachable_target_keeps_last_reachable_and_is_reported():
    env = make()
    agent = env.unwrapped.agent
    for _ in range(60):  # push the TCP backwards (-x, up) far beyond the 0.58 m reach envelope
        env.step(np.array([-1, 0, 0, 0, 1], dtype=np.float32))
        if agent.ik_unreachable.any():
            break
    else:
        pytest.fail("target never became unreachable")
    q_before = agent.robot.get_qpos().clone()
    env.step(np.array([-1, 0, 0, 0, 1], dtype=np.float32))
    assert agent.ik_unreachable.all()
    q = agent.robot.get_qpos()
    assert torch.isfinite(q).all()
    assert (q - q_before).abs().max() < 0.02  # held, not flung towards a bogus solution


@pytest.mark.parametrize("bad, msg", [
    (np.array([0, 0, np.nan, 0, 1], dtype=np.float32), "NaN"),
    (np.array([0, 0, np.inf, 0, 1], dtype=np.float32), "NaN or inf"),
    (np.zeros(4, dtype=np.float32), "shape"),
    (np.zeros((2, 5), dtype=np.float32), "shape"),
])
def test_bad_actions_raise_clear_errors(bad, msg):
    env = make()
    with pytest.raises(ValueError, match=msg):
        env.step(bad)


def test_unknown_control_mode_is_rejected():
    with pytest.raises(Exception, match="pd_nonsense"):
        gym.make("IRB120CubeBench-test", control_mode="pd_nonsense")


def test_all_control_modes_step():
    for mode in ["pd_ee_delta_tool", "pd_ee_target_delta_tool", "pd_joint_pos", "pd_joint_delta_pos",
                 "pd_ee_delta_pose"]:
        env = make(control_mode=mode)
        if mode == "pd_joint_pos":
            a = np.r_[IRB120Metalwork.keyframes["rest"].qpos[:6], 1.0].astype(np.float32)
        else:
            a = np.zeros(env.action_space.shape, dtype=np.float32)
        for _ in range(3):
            env.step(a)
        assert torch.isfinite(env.unwrapped.agent.robot.get_qpos()).all(), mode
        env.close()


# ------------------------------------------------------------------ grasp
def test_gripper_grasps_lifts_and_holds_cube():
    env = make()
    agent, cube = env.unwrapped.agent, env.unwrapped.cube
    # descend along the approach axis until the TCP is 3 mm above the cube centre
    for _ in range(40):
        gap = agent.tcp_pose.p[0, 2].item() - (CUBE_HALF + 0.003)
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
    assert z == pytest.approx(CUBE_HALF + 0.10, abs=0.012)
    assert agent.is_grasping(cube).item()
    assert 0.016 < agent.gripper_opening.item() < 0.021  # pads on the 20 mm cube (~1 mm contact penetration)
    assert agent.is_static().item()


# ------------------------------------------------------------------ camera
def red_pixels(rgb: torch.Tensor) -> int:
    rgb = rgb[0].int()
    return int(((rgb[..., 0] > 120) & (rgb[..., 1] < 60) & (rgb[..., 2] < 60)).sum())


def test_hand_camera_shapes_motion_and_sees_cube():
    env = make(obs_mode="rgbd")
    obs, _ = env.reset(seed=0)
    cam = obs["sensor_data"]["hand_camera"]
    assert cam["rgb"].shape == (1, 84, 84, 3) and cam["rgb"].dtype == torch.uint8
    assert cam["depth"].shape == (1, 84, 84, 1)
    # looking straight down at the cube from 24 cm: it is in view, near the image centre
    above = red_pixels(cam["rgb"])
    assert above >= 9  # a 2 cm cube seen from 21 cm with a 90 deg, 84 px camera spans ~4x4 px
    ys, xs = torch.nonzero(cam["rgb"][0, ..., 0].int() - cam["rgb"][0, ..., 1].int() > 100, as_tuple=True)
    assert abs(xs.float().mean().item() - 42) < 12
    depth_mm = cam["depth"][0, ys, xs, 0].float().median().item()
    assert 150 < depth_mm < 300  # cube top ~21 cm below the camera eye
    first_depth = cam["depth"][0].float().median().item()
    for _ in range(35):  # 35 cm sideways: the cube leaves the ~56 cm wide view of the floor
        obs, *_ = env.step(np.array([0, 1, 0, 0, 1], dtype=np.float32))
    for _ in range(6):  # descend 6 cm: the floor comes closer
        obs, *_ = env.step(np.array([1, 0, 0, 0, 1], dtype=np.float32))
    rgb, depth = obs["sensor_data"]["hand_camera"]["rgb"], obs["sensor_data"]["hand_camera"]["depth"]
    assert red_pixels(rgb) < above / 3
    assert depth[0].float().median().item() < first_depth - 40


def test_forward_shader_renders_what_minimal_renders():
    """The one-pass sensor shader is a speed-up, not a different look: along a random walk of the
    arm, RGB and depth match ManiSkill's two-pass ``minimal`` pack."""
    from maniskill_irb120.rendering import sensor_shader_config

    envs = [gym.make("TableClearing-IRB120-v1", obs_mode="rgbd"),
            gym.make("TableClearing-IRB120-v1", obs_mode="rgbd", sensor_configs=dict(hand_camera=dict(shader_pack="minimal")))]
    assert envs[0].unwrapped._sensors["hand_camera"].config.shader_pack.endswith("rgbd_forward")
    assert envs[1].unwrapped._sensors["hand_camera"].config.shader_pack == "minimal"
    obs = [e.reset(seed=3)[0] for e in envs]
    rng = np.random.default_rng(3)
    for step in range(40):
        if step % 8 == 0:
            (fw, mn) = [o["sensor_data"]["hand_camera"] for o in obs]
            assert fw["rgb"].dtype == torch.uint8 and fw["depth"].dtype == torch.int16
            diff = (fw["rgb"].int() - mn["rgb"].int()).abs()
            assert float((diff > 2).float().mean()) < 0.01, f"step {step}: {int(diff.max())} max RGB difference"
            assert torch.equal(fw["depth"], mn["depth"])
        a = rng.uniform(-1, 1, 5).astype(np.float32)
        obs = [e.step(a)[0] for e in envs]
    for e in envs:
        e.close()
    with pytest.raises(ValueError, match="unknown sensor shader"):
        sensor_shader_config("phong")


# ------------------------------------------------------------------ description, packaging, doctor
def test_urdf_regenerates_identically(tmp_path):
    used = Path(rd.urdf_path())
    again = rd.xacro_to_urdf(used.parent / "meshes")
    assert again == used.read_text()
    meshes = rd.write_meshes(tmp_path)
    for link, _ in meshes.items():
        assert (tmp_path / f"{link}.obj").read_text() == (used.parent / "meshes" / f"{link}.obj").read_text()


def test_robot_is_low_poly():
    assert 300 < rd.triangle_count() < 3000


@pytest.mark.slow
def test_wheel_ships_assets(tmp_path):
    import subprocess
    import sys

    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(tmp_path), str(REPO)], check=True)
    (whl,) = tmp_path.glob("maniskill_irb120-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    for f in ["irb120_metalwork.urdf.xacro", "geometry.xacro", "physics.xacro", "gripper.xacro", "macros.xacro"]:
        assert f"maniskill_irb120/assets/irb120_metalwork/{f}" in names
    for f in ["gbuffer.vert", "gbuffer.frag"]:
        assert f"maniskill_irb120/assets/shaders/rgbd_forward/{f}" in names


def test_doctor_finds_render_device():
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "maniskill_irb120.cli", "doctor", "--json"], capture_output=True,
                         text=True, timeout=120)
    r = json.loads(out.stdout)
    assert out.returncode == 0, out.stdout + out.stderr
    assert r["render_ok"] and r["render_device"]["supported"], r
    assert r["render_probe"]["centre_depth_m"] == pytest.approx(0.4, abs=0.01)
