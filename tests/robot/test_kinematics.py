"""IRB 120 kinematics: forward kinematics against ABB's published chain, joint data, the closed-form
IK and its numpy/torch backends, and the joint-speed guard."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from mani_skill.utils.geometry.rotation_conversions import matrix_to_quaternion as ms_matrix_to_quaternion
from mani_skill.utils.geometry.rotation_conversions import quaternion_to_matrix

from maniskill_irb120.robot import description as rd
from maniskill_irb120.robot.kinematics import matrix_to_quaternion


def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    m = {
        "x": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }[axis]
    t = np.eye(4)
    t[:3, :3] = m
    return t


def trans(x=0.0, z=0.0) -> np.ndarray:
    t = np.eye(4)
    t[0, 3], t[2, 3] = x, z
    return t


def abb_flange(q) -> np.ndarray:
    """ABB's published IRB 120 chain: 0.290 base-axis2, 0.270 axis2-3, 0.070 offset, 0.302 to wrist, 0.072 flange."""
    return (
        trans(z=0.290)
        @ rot("z", q[0])
        @ rot("y", q[1])
        @ trans(z=0.270)
        @ rot("y", q[2])
        @ trans(x=0.302, z=0.070)
        @ rot("x", q[3])
        @ rot("y", q[4])
        @ trans(x=0.072)
        @ rot("x", q[5])
    )


CONFIGS = [
    np.zeros(6),
    [0.5, 0.3, -0.2, 0.4, 0.6, 0.7],
    [-1.2, -0.8, 0.9, -1.5, 1.1, -2.0],
    [2.5, 1.2, -1.5, 2.0, -1.8, 5.0],
    [0.0, 0.33, 0.46, 0.0, 0.78, 0.0],
    [-2.8, -1.9, 1.2, 2.7, 2.0, -6.5],
]


def test_flange_fk_matches_abb_chain(bench):
    env = bench.make()
    robot = env.unwrapped.agent.robot
    residuals = []
    for q in CONFIGS:
        robot.set_qpos(torch.tensor([list(q) + [0.0, 0.0]], dtype=torch.float32))
        sim = robot.links_map["link6"].pose.to_transformation_matrix()[0].double().numpy()
        ref = abb_flange(q)
        residuals.append(np.linalg.norm(sim[:3, 3] - ref[:3, 3]))
        assert np.allclose(sim[:3, :3], ref[:3, :3], atol=1e-4)
    # 0.6 mm: the original report's axis-3 offset is 0.0706 m where ABB quotes 0.070 m
    assert max(residuals) < 1e-3, residuals


def test_joint_limits_and_speeds_match_abb(bench):
    env = bench.make()
    lim = env.unwrapped.agent.robot.get_qlimits()[0].numpy()
    deg = np.degrees(lim[:6])
    np.testing.assert_allclose(
        deg, [[-165, 165], [-110, 110], [-110, 70], [-160, 160], [-120, 120], [-400, 400]], atol=1e-3
    )
    np.testing.assert_allclose(lim[6:], [[0, 0.012], [0, 0.012]], atol=1e-7)
    import xml.etree.ElementTree as ET

    vel = {
        j.get("name"): float(j.find("limit").get("velocity"))
        for j in ET.parse(rd.urdf_path()).getroot().iter("joint")
        if j.find("limit") is not None
    }
    np.testing.assert_allclose(
        np.degrees([vel[f"joint_{i}"] for i in range(1, 7)]), [250, 250, 250, 320, 320, 420], rtol=1e-6
    )


def test_own_kinematics_matches_pytorch_kinematics():
    import pytorch_kinematics as pk

    from maniskill_irb120.robot.kinematics import SerialChain

    chain = SerialChain(rd.urdf_path(), "tcp")
    ref = pk.build_serial_chain_from_urdf(Path(rd.urdf_path()).read_bytes(), end_link_name="tcp")
    q = torch.as_tensor(np.array(CONFIGS), dtype=torch.float32)
    tip, jac = chain.fk_with_jacobian(q)
    jac_ref, tip_ref = ref.jacobian(q, ret_eef_pose=True)
    torch.testing.assert_close(tip, tip_ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(jac, jac_ref, atol=1e-5, rtol=0)


def test_closed_form_ik_inverts_fk_on_its_branch():
    from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK

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
    from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK

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


def test_controller_step_numpy_and_torch_backends_agree(bench):
    """The fused FK/delta/IK/speed-check pass: numpy (CPU sim) and torch (GPU sim) agree."""
    from maniskill_irb120.robot.kinematics import ArmIK

    env = bench.make()
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
    from maniskill_irb120.robot.kinematics import SerialChain, SphericalWristIK

    chain = SerialChain(rd.urdf_path(), "tcp", dtype=torch.float64)
    ik = SphericalWristIK(chain)
    q0 = torch.tensor([[0.2, 0.3, 0.1, 0.4, 0.02, -0.3]], dtype=torch.float64)
    q_goal = q0.clone()
    q_goal[0, 4] = -0.02
    sol, ok = ik.solve(chain.forward_kinematics(q_goal), q0)
    assert bool(ok.all())
    torch.testing.assert_close(sol, q_goal, atol=1e-6, rtol=0)


def test_tool_step_needing_a_too_fast_joint_is_refused(bench):
    """Wrist centre 2 mm in front of axis 1: a 6 mm step back across the axis needs axis 1 to turn half a
    turn in one 50 ms control period (ABB: 250 deg/s): refused and flagged, the arm keeps its target;
    a 1 mm step forward is fine."""
    from maniskill_irb120.robot.kinematics import SphericalWristIK

    env = bench.make()
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
