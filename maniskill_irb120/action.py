"""The one home of the action space, ``pd_ee_delta_tool``: the original report's tool-frame action.

``[dx, dy, dz, yaw, gripper]`` in [-1, 1]: a translation along the TCP's own axes of up to ±1 cm per axis, a
rotation about the approach axis (TCP x) of up to ±10° (the original report's Table 4.1), and the gripper
(> 0 opens). Everything that produces, converts or executes such an action imports it from here: the sim's
controller, the scripted experts, the world-frame wrapper, and, on a robot PC, the ABB client and its safety
envelope. That is why this module needs numpy and torch only (no ManiSkill, no SAPIEN).

A translation expressed in world axes is a product of the tool's rotation and a world vector; rotated into the
tool frame it can leave the unit box, so it is shrunk uniformly (its direction kept) rather than clipped per
axis, which would bend a straight-line motion into a tray wall.
"""

from __future__ import annotations

import math

import numpy as np
import torch

TOOL_POS_LIMIT = 0.01
"""metres per unit action along each tool axis"""
TOOL_ROT_LIMIT = math.radians(10.0)
"""radians per unit action about the approach axis"""
ACTION_DIM = 5


def scale_tool_action(action, pos_limit: float = TOOL_POS_LIMIT, rot_limit: float = TOOL_ROT_LIMIT):
    """Normalised tool actions (..., 4) in [-1, 1] → metres along the tool axes and radians about the approach
    axis: clipped to the box, then scaled (ManiSkill's normalised-action convention for symmetric limits).
    numpy or torch."""
    lib = torch if isinstance(action, torch.Tensor) else np
    limits = lib.asarray([pos_limit] * 3 + [rot_limit], dtype=action.dtype)
    if lib is torch:
        limits = limits.to(action.device)
    return lib.clip(action, -1.0, 1.0) * limits


def gripper_opens(value):
    """The gripper command of an action: > 0 opens, <= 0 closes (the original report's ``open`` flag)."""
    return value > 0


def apply_tool_delta(xp, ref, action):
    """``ref · Δ`` for (N,4,4) poses and (N,4) actions in metres and radians: Δ translates by action[:3]
    in the tool frame, then rotates by action[3] about the tool's x axis (the original report's
    ``multiplyTransforms(current, delta)``); ``xp`` is numpy or torch."""
    r = ref[:, :3, :3]
    c, s = xp.cos(action[:, 3:4]), xp.sin(action[:, 3:4])
    pos = ref[:, :3, 3] + (r @ action[:, :3, None])[..., 0]
    cols = [r[:, :, 0], c * r[:, :, 1] + s * r[:, :, 2], c * r[:, :, 2] - s * r[:, :, 1], pos]
    # concatenate rather than stack: the same numbers, and numpy's stack costs several microseconds at N = 1
    return xp.concatenate([xp.concatenate([c[..., None] for c in cols], 2), ref[:, 3:]], 1)


def quaternion_to_rotation(q):
    """(N, 3, 3) rotation matrices of (N, 4) wxyz quaternions (numpy or torch; not necessarily unit): the same
    arithmetic as ManiSkill's (pytorch3d's) ``quaternion_to_matrix``, so both give identical numbers."""
    xp = torch if isinstance(q, torch.Tensor) else np
    r, i, j, k = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    two_s = 2.0 / (q * q).sum(-1)
    o = xp.stack(
        (
            1 - two_s * (j * j + k * k),
            two_s * (i * j - k * r),
            two_s * (i * k + j * r),
            two_s * (i * j + k * r),
            1 - two_s * (i * i + k * k),
            two_s * (j * k - i * r),
            two_s * (i * k - j * r),
            two_s * (j * k + i * r),
            1 - two_s * (i * i + j * j),
        ),
        -1,
    )
    return o.reshape(q.shape[:-1] + (3, 3))


def tcp_rotation(tcp_pose: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) TCP rotation from (N, 7) raw poses (position, wxyz quaternion): the tool frame every
    tool↔world conversion uses, on the sim (the agent's TCP) and on a robot (FK of the joints it reports)."""
    return quaternion_to_rotation(tcp_pose[:, 3:7])


def fit_unit_box(v: torch.Tensor) -> torch.Tensor:
    """``v`` (..., k) shrunk uniformly until its largest component is at most 1 in magnitude (direction kept)."""
    return v / v.abs().amax(dim=-1, keepdim=True).clamp(min=1.0)


def world_to_tool(action: torch.Tensor, tcp_rot: torch.Tensor) -> torch.Tensor:
    """(N, 5) actions whose translation is in world axes → tool-frame actions, for TCP rotations (N, 3, 3)."""
    out = action.clone()
    out[:, :3] = fit_unit_box((tcp_rot.transpose(1, 2) @ action[:, :3].unsqueeze(2)).squeeze(2))
    return out


def tool_to_world(action: torch.Tensor, tcp_rot: torch.Tensor) -> torch.Tensor:
    """The inverse map (labels: the expert's tool-frame action expressed in world axes)."""
    out = action.clone()
    out[:, :3] = fit_unit_box((tcp_rot @ action[:, :3].unsqueeze(2)).squeeze(2))
    return out


def action_from_world_motion(
    displacement: torch.Tensor,
    yaw: torch.Tensor,
    gripper: torch.Tensor,
    tcp_rot: torch.Tensor,
    pos_limit: float = TOOL_POS_LIMIT,
    rot_limit: float = TOOL_ROT_LIMIT,
) -> torch.Tensor:
    """(N, 5) tool actions that move the TCP by ``displacement`` (N, 3, metres, world axes) as far as one step
    allows, in a straight line (rotated into the tool frame, then fitted to the unit box), turn it by ``yaw``
    (N, radians, clipped to one step) and command ``gripper`` (N, +1 open / -1 close): a scripted controller's
    way to act in this action space."""
    local = fit_unit_box((tcp_rot.transpose(1, 2) @ displacement.unsqueeze(2)).squeeze(2) / pos_limit)
    rot = (yaw / rot_limit).clamp(-1, 1)
    return torch.cat([local, rot.unsqueeze(1), gripper.unsqueeze(1)], dim=1).clamp(-1, 1)
