"""Batched kinematics of a serial chain: FK, geometric Jacobian, closed-form IK (CPU and CUDA).

pytorch_kinematics computes the same FK and Jacobian (the tests check they agree), but its Jacobian
costs ~2.8 ms per call on one CPU core for this 6-axis chain. These classes precompute the chain's
fixed transforms once and evaluate everything in a few dozen batched array ops.

FK and the closed-form IK are written once against the array operations numpy and torch share
(``xp`` below is either module) and run in numpy for CPU tensors, in torch otherwise: with
ManiSkill's CPU sim (one env) the arrays hold a single pose and each torch op costs ~2-8 us of
dispatch, numpy ~0.5-1 us, so the same math is several times faster; on CUDA (thousands of envs)
it stays on the device.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch

from maniskill_irb120.action import apply_tool_delta, quaternion_to_rotation


def run_batched(fn, consts, *tensors: torch.Tensor):
    """``fn(xp, c, *arrays)`` on numpy views of CPU tensors (results back as tensors, no copies) or
    on the tensors themselves on other devices. ``consts(xp, like)`` gives ``c`` for that backend."""
    like = tensors[0]
    if like.device.type == "cpu":
        arrays = [t.detach().numpy() for t in tensors]
        out = fn(np, consts(np, arrays[0]), *arrays)
        return (
            tuple(torch.from_numpy(np.ascontiguousarray(o)) for o in out)
            if isinstance(out, tuple)
            else torch.from_numpy(np.ascontiguousarray(out))
        )
    return fn(torch, consts(torch, like), *tensors)


def columns(xp, arrays):
    """``xp.stack(arrays, 1)`` for (N,) arrays, the same numbers: numpy's ``stack`` is a Python function costing
    several microseconds at N = 1, its ``concatenate`` one call."""
    if xp is np:
        return np.concatenate([a[:, None] for a in arrays], 1)
    return torch.stack(arrays, 1)


def backend_consts(cache: dict, xp, like, build) -> SimpleNamespace:
    """Constants for one backend, built once per (module, dtype, device) and cached in ``cache``:
    ``build(conv)`` gets ``conv(tensor)``, which returns that tensor as an ``xp`` array like ``like``."""
    key = (xp.__name__, str(like.dtype), str(getattr(like, "device", "cpu")))
    if key not in cache:
        if xp is np:
            cache[key] = build(lambda t: t.detach().cpu().numpy().astype(like.dtype))
        else:
            cache[key] = build(lambda t: t.to(device=like.device, dtype=like.dtype))
    return cache[key]


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _origin(joint: ET.Element) -> np.ndarray:
    t = np.eye(4)
    o = joint.find("origin")
    if o is not None:
        t[:3, :3] = _rpy_matrix(*[float(v) for v in o.get("rpy", "0 0 0").split()])
        t[:3, 3] = [float(v) for v in o.get("xyz", "0 0 0").split()]
    return t


class SerialChain:
    """Revolute chain from ``root`` to ``tip`` parsed from a URDF; fixed joints are folded in."""

    def __init__(self, urdf_file: str, tip: str, device="cpu", dtype=torch.float32):
        root_el = ET.parse(urdf_file).getroot()
        by_child = {j.find("child").get("link"): j for j in root_el.findall("joint")}
        path, link = [], tip
        while link in by_child:
            path.append(by_child[link])
            link = by_child[link].find("parent").get("link")
        path.reverse()
        self.root = link
        offsets, axes, names, lower, upper, velocity = [], [], [], [], [], []
        pending = np.eye(4)
        for j in path:
            pending = pending @ _origin(j)
            if j.get("type") == "fixed":
                continue
            if j.get("type") != "revolute":
                raise ValueError(f"joint {j.get('name')} of type {j.get('type')} is not supported")
            offsets.append(pending)
            pending = np.eye(4)
            axes.append([float(v) for v in j.find("axis").get("xyz").split()])
            lim = j.find("limit")
            lower.append(float(lim.get("lower")))
            upper.append(float(lim.get("upper")))
            velocity.append(float(lim.get("velocity", "inf")))
            names.append(j.get("name"))
        self.joint_names = names
        self.dof = len(names)
        as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
        self.offsets = as_t(np.stack(offsets))  # (dof, 4, 4)
        self.tip_offset = as_t(pending)  # fixed transform after the last joint
        ax = np.asarray(axes) / np.linalg.norm(axes, axis=1, keepdims=True)
        k = np.zeros((self.dof, 3, 3))
        k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -ax[:, 2], ax[:, 1], -ax[:, 0]
        k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = ax[:, 2], -ax[:, 1], ax[:, 0]
        self.axes = as_t(ax)
        self.K, self.K2 = as_t(k), as_t(k @ k)
        self.lower, self.upper, self.velocity = as_t(lower), as_t(upper), as_t(velocity)
        self._consts: dict = {}
        self._derive()

    def _derive(self) -> None:
        self.off_r = self.offsets[:, :3, :3]
        # per joint: [offset translation | offset rotation · axis], both expressed before the offset
        self.off_pc = torch.stack([self.offsets[:, :3, 3], (self.off_r @ self.axes[..., None])[..., 0]], -1)

    def to(self, device) -> SerialChain:
        for name in ("offsets", "tip_offset", "axes", "K", "K2", "lower", "upper", "velocity"):
            setattr(self, name, getattr(self, name).to(device))
        self._consts = {}
        self._derive()
        return self

    def joint_rotations(self, q: torch.Tensor) -> torch.Tensor:
        s, c = torch.sin(q)[..., None, None], torch.cos(q)[..., None, None]
        eye = torch.eye(3, dtype=q.dtype, device=q.device)
        return eye + s * self.K + (1 - c) * self.K2  # (N, dof, 3, 3) Rodrigues

    def fk_with_jacobian(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Tip pose (N,4,4) in the root frame and geometric Jacobian (N,6,dof): rows [v; ω].

        With A_i the orientation after joint i, A_i = A_{i-1}·(R_off,i·Rot_i): one batched product for
        all (R_off·Rot) factors, ``dof`` sequential 3x3 products, then every joint origin and axis from
        one batched multiply of the A_{i-1} with the constant [p_off,i | R_off,i·axis_i] and a cumsum.
        """
        b = self.off_r @ self.joint_rotations(q)  # (N, dof, 3, 3)
        n = q.shape[0]
        a = [b[:, 0]]
        for i in range(1, self.dof):
            a.append(a[-1] @ b[:, i])
        eye = torch.eye(3, dtype=q.dtype, device=q.device).expand(n, 1, 3, 3)
        a_prev = torch.cat([eye, torch.stack(a[:-1], 1)], 1)  # orientation before each joint's offset
        v = a_prev @ self.off_pc  # (N, dof, 3, 2): offset translation and joint axis, in the root frame
        origins = torch.cumsum(v[..., 0], 1)  # (N, dof, 3)
        axes = v[..., 1]
        tip = torch.zeros(n, 4, 4, dtype=q.dtype, device=q.device)
        tip[:, :3, :3] = a[-1] @ self.tip_offset[:3, :3]
        tip[:, :3, 3] = origins[:, -1] + a[-1] @ self.tip_offset[:3, 3]
        tip[:, 3, 3] = 1
        jv = torch.linalg.cross(axes, tip[:, None, :3, 3] - origins, dim=2)
        return tip, torch.cat([jv, axes], 2).transpose(1, 2)

    def consts(self, xp, like) -> SimpleNamespace:
        """The chain's constants as ``xp`` arrays of ``like``'s dtype (and device), cached."""
        return backend_consts(
            self._consts,
            xp,
            like,
            lambda conv: SimpleNamespace(
                off_r=conv(self.offsets[:, :3, :3]),
                # no joint origin rotates (the IRB 120's URDF): fk skips the product with identities
                off_r_eye=bool(
                    torch.equal(self.offsets[:, :3, :3], torch.eye(3).to(self.offsets).expand(self.dof, 3, 3))
                ),
                off_p=conv(self.offsets[:, :3, 3]),
                K=conv(self.K),
                K2=conv(self.K2),
                eye3=conv(torch.eye(3)),
                tip_r=conv(self.tip_offset[:3, :3]),
                tip_p=conv(self.tip_offset[:3, 3]),
                last_row=conv(torch.tensor([[[0.0, 0.0, 0.0, 1.0]]])),
                lower=conv(self.lower),
                upper=conv(self.upper),
                one=conv(torch.tensor(1.0)),
            ),
        )

    @staticmethod
    def fk(xp, c: SimpleNamespace, q):
        """Tip pose (N,4,4) for joint angles (N,dof), with ``xp`` numpy or torch."""
        s, co = xp.sin(q)[..., None, None], xp.cos(q)[..., None, None]
        b = c.eye3 + s * c.K + (1 - co) * c.K2  # (N, dof, 3, 3): Rodrigues
        if not c.off_r_eye:
            b = c.off_r @ b  # the offset first
        a, p = b[:, 0], c.off_p[0]
        for i in range(1, b.shape[1]):
            p = p + a @ c.off_p[i]
            a = a @ b[:, i]
        top = xp.concatenate([a @ c.tip_r, (p + a @ c.tip_p)[..., None]], 2)
        last = c.last_row if top.shape[0] == 1 else xp.broadcast_to(c.last_row, (top.shape[0], 1, 4))
        return xp.concatenate([top, last], 1)

    def forward_kinematics(self, q: torch.Tensor) -> torch.Tensor:
        """Tip pose (N,4,4) in the root frame (no Jacobian)."""
        return run_batched(self.fk, self.consts, q)


class SphericalWristIK:
    """Closed-form inverse kinematics of a 6R arm of the IRB 120's structure, batched (numpy or torch).

    Structure (checked at construction, else ``ValueError``): axis 1 vertical (z), axes 2 and 3 parallel
    (y) with no shoulder offset, axes 4-6 (x, y, x) meeting in one wrist centre, no rotations in the
    joint origins. Position then decouples from orientation: axes 1-3 place the wrist centre (a planar
    two-link problem), axes 4-6 are X-Y-X Euler angles of the remaining rotation. That is one pass of
    ~60 small tensor ops instead of iterating FK + Jacobian + a 6x6 solve, and the answer is exact.

    Of the up to eight solutions, the one on ``q0``'s shoulder (front/back) and elbow (up/down) branch
    and the nearer of the two wrist solutions is returned, axis 6 unwrapped to the turn nearest ``q0``:
    for small steps, the solution damped least squares from ``q0`` converges to.
    """

    SINGULAR = 1e-6

    def __init__(self, chain: SerialChain):
        if chain.dof != 6:
            raise ValueError(f"closed-form IK needs 6 revolute joints, chain has {chain.dof}")
        off = chain.offsets.detach().cpu().double()
        ax = chain.axes.detach().cpu().double()
        expected_axes = torch.tensor(
            [[0, 0, 1], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], dtype=torch.float64
        )
        p = off[:, :3, 3]
        structure_ok = (
            torch.allclose(ax, expected_axes, atol=1e-9)
            and torch.allclose(off[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(6, 3, 3), atol=1e-9)
            and torch.allclose(
                p[:3, :2], torch.zeros(3, 2, dtype=torch.float64), atol=1e-9
            )  # on axis 1, no shoulder offset
            and torch.allclose(p[3:, 1], torch.zeros(3, dtype=torch.float64), atol=1e-9)
            and torch.allclose(
                p[4:, 2], torch.zeros(2, dtype=torch.float64), atol=1e-9
            )  # axes 4 and 6 through the wrist
        )
        if not structure_ok:
            raise ValueError("chain is not an axis-1-vertical, parallel-axes-2/3, spherical-wrist 6R arm")
        self.chain = chain
        self.h = float(p[0, 2] + p[1, 2])  # height of axis 2 above the root
        self.a2 = float(p[2, 2])  # axis 2 to axis 3
        d, e = float(p[3, 0] + p[4, 0]), float(p[3, 2])  # axis 3 to the wrist centre, in axis 3's frame
        self.L, self.phi = math.hypot(d, e), math.atan2(e, d)
        tip = chain.tip_offset.detach().cpu().double()
        r_to, p_to = tip[:3, :3], tip[:3, 3]
        # the wrist centre in the tip frame: fixed, since it lies on axis 6
        w6 = torch.tensor([-float(p[5, 0]), 0.0, 0.0], dtype=torch.float64)
        self.w_tip = (r_to.T @ (w6 - p_to)).to(chain.axes)
        self.r_to = r_to.to(chain.axes)
        self._consts: dict = {}

    def consts(self, xp, like) -> SimpleNamespace:
        def build(conv) -> SimpleNamespace:
            c = self.chain.consts(xp, like)
            return SimpleNamespace(
                lower=c.lower,
                upper=c.upper,
                one=c.one,
                w_tip=conv(self.w_tip),
                r_to_t=conv(self.r_to.T.contiguous()),
                h=self.h,
                a2=self.a2,
                L=self.L,
                phi=self.phi,
                singular=self.SINGULAR,
            )

        return backend_consts(self._consts, xp, like, build)

    def solve(self, target: torch.Tensor, q0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint angles (N,6) reaching ``target`` (N,4,4, tip in the root frame) on ``q0``'s branch, and
        (N,) whether that solution exists within the joint limits. Where it does not, the row is ``q0``."""
        return run_batched(self._solve, self.consts, target, q0)

    @staticmethod
    def _solve(xp, c: SimpleNamespace, target, q0):
        rot, pos = target[:, :3, :3], target[:, :3, 3]
        w = pos + (rot @ c.w_tip[:, None])[..., 0]  # wrist centre in the root frame
        a2, L, phi, one = c.a2, c.L, c.phi, c.one
        # branches of q0: shoulder (wrist centre in front of axis 1 or behind) and elbow
        beta0 = phi - q0[:, 2]
        reach0 = a2 * xp.sin(q0[:, 1]) + L * xp.cos(q0[:, 1] - beta0)  # wrist centre's x in the arm plane
        shoulder = xp.where(reach0 >= 0, one, -one)
        elbow_up = xp.cos(beta0) >= 0

        rxy = xp.sqrt(w[:, 0] ** 2 + w[:, 1] ** 2)
        q1 = xp.where(rxy > c.singular, xp.atan2(shoulder * w[:, 1], shoulder * w[:, 0]), q0[:, 0])
        r, z = shoulder * rxy, w[:, 2] - c.h
        sin_b = (r * r + z * z - (a2 * a2 + L * L)) / (2 * a2 * L)
        reachable = xp.abs(sin_b) <= 1.0
        b_principal = xp.asin(xp.minimum(xp.maximum(sin_b, -one), one))  # a clip (numpy's clip is slow at N = 1)
        beta = xp.where(elbow_up, b_principal, math.pi - b_principal)
        q2 = xp.atan2(r, z) - xp.atan2(L * xp.cos(beta), a2 + L * xp.sin(beta))
        q2 = xp.remainder(q2 + math.pi, 2 * math.pi) - math.pi
        q3 = phi - beta

        # remaining rotation R_36 = R_3^T R_6 with R_3 = Rz(q1) Ry(q2 + q3) and R_6 = R_tip R_to^T
        c1, s1, c23, s23 = xp.cos(q1), xp.sin(q1), xp.cos(q2 + q3), xp.sin(q2 + q3)
        # rows of R_3^T: (c1 c23, s1 c23, -s23), (-s1, c1, 0), (c1 s23, s1 s23, c23)
        r3t = columns(xp, [c1 * c23, s1 * c23, -s23, -s1, c1, 0 * c1, c1 * s23, s1 * s23, c23]).reshape(-1, 3, 3)
        m = r3t @ rot @ c.r_to_t
        # two wrist solutions: q5 >= 0 and its flip (q4 + pi, -q5, q6 + pi); take the one nearer q0, so that
        # passing through the wrist singularity (q5 = 0) moves q5 through zero instead of turning q4 and
        # q6 half a turn. At the singularity only q4 + q6 is defined: keep q4 where it was.
        sb = xp.sqrt(m[:, 1, 0] ** 2 + m[:, 2, 0] ** 2)
        singular = sb < c.singular
        q4 = xp.where(singular, q0[:, 3], xp.atan2(m[:, 1, 0], -m[:, 2, 0]))
        q5 = xp.atan2(sb, m[:, 0, 0])
        q6 = xp.where(singular, xp.atan2(m[:, 2, 1], m[:, 1, 1]) - q0[:, 3], xp.atan2(m[:, 0, 1], m[:, 0, 2]))
        half = xp.where(singular, 0 * q4, xp.where(q4 > 0, -math.pi + 0 * q4, math.pi + 0 * q4))
        wq = columns(xp, [q4, q5, q6, q4 + half, -q5, q6 - half]).reshape(-1, 2, 3)  # (N, 2, 3)
        nearest = np.rint if xp is np else torch.round  # both round half to even; rint is numpy's ufunc, round is not
        wq6 = wq[:, :, 2] + 2 * math.pi * nearest((q0[:, 5:6] - wq[:, :, 2]) / (2 * math.pi))  # turn nearest q0
        wq = xp.concatenate([wq[:, :, :2], wq6[:, :, None]], 2)
        out = ((wq < c.lower[3:]) | (wq > c.upper[3:])).any(2)
        cost = xp.abs(wq - q0[:, None, 3:]).sum(2) + 100.0 * out
        best = xp.where((cost[:, 1] < cost[:, 0])[:, None], wq[:, 1], wq[:, 0])
        q = xp.concatenate([columns(xp, [q1, q2, q3]), best], 1)
        ok = reachable & ((q >= c.lower) & (q <= c.upper)).all(1)
        return xp.where(ok[:, None], q, q0).astype(q0.dtype) if xp is np else xp.where(ok[:, None], q, q0), ok


@dataclass
class DLSParams:
    iterations: int = 6
    damping: float = 1e-3
    pos_tol: float = 2e-4
    """metres"""
    rot_tol: float = math.radians(0.2)
    """radians"""


IK_METHODS = ("auto", "closed_form", "dls")


class ArmIK:
    """The one inverse-kinematics interface: :meth:`solve` (a pose) and :meth:`tool_step` (a tool-frame
    delta from the current or a given pose, FK + delta + IK in one pass). Behind it: the closed form for
    the IRB 120's spherical wrist (exact, one pass) or damped least squares for any other serial chain.

    ``method``: "closed_form", "dls" or "auto" (closed form when the chain has the structure).
    ``max_joint_step`` (dof,): a solution needing a larger move from ``q0`` on any joint is not ok (a real
    arm could not follow it within one control period; such jumps happen only at singularities).
    """

    def __init__(
        self,
        chain: SerialChain,
        method: str = "auto",
        dls: DLSParams | None = None,
        max_joint_step: torch.Tensor | None = None,
    ):
        if method not in IK_METHODS:
            raise ValueError(f"ik_solver={method!r} is not one of {IK_METHODS}")
        self.chain, self.dls = chain, dls or DLSParams()
        self.max_joint_step = (
            torch.full_like(chain.lower, math.inf)
            if max_joint_step is None
            else torch.as_tensor(max_joint_step).to(chain.lower)
        )
        self.closed_form = None
        if method != "dls":
            try:
                self.closed_form = SphericalWristIK(chain)
            except ValueError:
                if method == "closed_form":
                    raise
        self.method = "closed_form" if self.closed_form is not None else "dls"
        self._consts: dict = {}

    def consts(self, xp, like) -> SimpleNamespace:
        return backend_consts(
            self._consts,
            xp,
            like,
            lambda conv: SimpleNamespace(
                chain=self.chain.consts(xp, like),
                ik=self.closed_form.consts(xp, like),
                max_step=conv(self.max_joint_step),
            ),
        )

    def solve(self, target: torch.Tensor, q0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint angles (N,dof) reaching ``target`` (N,4,4, tip in the root frame) from ``q0``, and (N,)
        whether they do within the joint limits (closed form: ``q0``'s branch; rows that fail are ``q0``)."""
        if self.method == "closed_form":
            return self.closed_form.solve(target, q0)
        return self.solve_dls(target, q0)

    def solve_dls(self, target: torch.Tensor, q0: torch.Tensor, fk0=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Damped least squares from ``q0`` (``fk0``: ``chain.fk_with_jacobian(q0)`` if already known).

        The rotation error is the vee of the skew part of R_target·R_currentᵀ: its direction is the
        rotation axis and its norm sin(angle), which equals the angle to 1e-5 rad at the sub-degree
        errors IK iterates on, at a fraction of the cost of a quaternion/axis-angle round trip.
        """
        p, chain = self.dls, self.chain
        q = q0.clone()
        eye = torch.eye(6, device=q.device, dtype=q.dtype)
        for i in range(p.iterations + 1):
            cur, jac = fk0 if (i == 0 and fk0 is not None) else chain.fk_with_jacobian(q)
            err_p = target[:, :3, 3] - cur[:, :3, 3]
            r = target[:, :3, :3] @ cur[:, :3, :3].transpose(1, 2)
            err_r = 0.5 * torch.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], 1)
            # a trace below 1 means an error above 90 deg, where sin() is ambiguous: never "converged"
            converged = (
                (err_p.norm(dim=1) < p.pos_tol)
                & (err_r.norm(dim=1) < p.rot_tol)
                & (r.diagonal(dim1=1, dim2=2).sum(1) > 1.0)
            )
            # early exit on the CPU only: on CUDA the check would wait for the GPU every iteration
            if i == p.iterations or (q.device.type == "cpu" and bool(converged.all())):
                break
            err = torch.cat([err_p, err_r], dim=1)
            jjt = jac @ jac.transpose(1, 2) + (p.damping**2) * eye
            dq = (jac.transpose(1, 2) @ torch.linalg.solve(jjt, err.unsqueeze(-1))).squeeze(-1)
            q = torch.clamp(q + dq, chain.lower, chain.upper)
        return q, converged

    def tool_step(
        self, q0: torch.Tensor, action: torch.Tensor, ref: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Solve for ``ref · Δ(action)`` (see :func:`apply_tool_delta`; ``ref``: FK of ``q0`` when None).
        Returns (joint angles, ok: reachable and within ``max_joint_step`` of ``q0``, target pose)."""
        if self.method == "closed_form":
            if ref is None:
                return run_batched(self._closed_form_tool_step, self.consts, q0, action)
            return run_batched(self._closed_form_tool_step, self.consts, q0, action, ref)
        fk0 = self.chain.fk_with_jacobian(q0)
        target = apply_tool_delta(torch, fk0[0] if ref is None else ref, action)
        q, ok = self.solve_dls(target, q0, fk0)
        return q, ok & ((q - q0).abs() <= self.max_joint_step).all(1), target

    @staticmethod
    def _closed_form_tool_step(xp, c: SimpleNamespace, q0, action, ref=None):
        """FK, tool delta, IK and the joint-speed check in one pass (numpy on CPU, torch on CUDA)."""
        target = apply_tool_delta(xp, SerialChain.fk(xp, c.chain, q0) if ref is None else ref, action)
        q, ok = SphericalWristIK._solve(xp, c.ik, target, q0)
        return q, ok & (xp.abs(q - q0) <= c.max_step).all(1), target


def matrix_to_quaternion(m: torch.Tensor) -> torch.Tensor:
    """wxyz unit quaternions (w >= 0) of (N,3,3) rotation matrices, with no host synchronisation.

    ManiSkill's (pytorch3d's) version picks the best-conditioned of four candidates by boolean-mask
    indexing, which waits for the GPU; this picks it with ``gather``. Called on every observation in
    ``pd_ee_target_delta_tool`` (the controller state is part of the proprioception)."""
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    q_abs = (
        torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], 1)
        .clamp_min(0)
        .sqrt()
    )  # 2|w|, 2|x|, 2|y|, 2|z|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s10, s02, s21 = m[:, 1, 0] + m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 2, 1] + m[:, 1, 2]
    a0, a1, a2, a3 = (q_abs[:, i] ** 2 for i in range(4))
    cand = torch.stack(
        [
            torch.stack(row, 1)
            for row in ((a0, d21, d02, d10), (d21, a1, s10, s02), (d02, s10, a2, s21), (d10, s02, s21, a3))
        ],
        1,
    )  # (N, 4, 4)
    cand = cand / (2 * q_abs.clamp_min(0.1))[:, :, None]
    best = q_abs.argmax(1)[:, None, None].expand(-1, 1, 4)
    q = torch.gather(cand, 1, best)[:, 0]
    return q * torch.where(q[:, :1] < 0, -1.0, 1.0)


def quat_to_matrix(q) -> np.ndarray:
    """(3, 3) rotation of a wxyz quaternion (normalised first), numpy; ManiSkill's conversion underneath."""
    q = torch.as_tensor(np.asarray(q, dtype=np.float64))
    return quaternion_to_rotation(q / q.norm()).numpy()


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """wxyz quaternion (w >= 0) of a (3, 3) rotation, numpy."""
    return matrix_to_quaternion(torch.as_tensor(m[None], dtype=torch.float64))[0].numpy()


def pose_mm(pos_mm, quat) -> np.ndarray:
    """(4, 4) pose in metres from RAPID's units: a position in mm and a wxyz quaternion."""
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = quat_to_matrix(quat), np.asarray(pos_mm, dtype=np.float64) / 1000
    return t
