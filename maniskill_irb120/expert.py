"""Scripted expert for TableClearing-IRB120-v1.

It reads privileged state (object pose, tray centres) but acts only through ``pd_ee_delta_tool``
actions in [-1, 1]: a world-frame displacement is rotated into the TCP frame (Rᵀ·d), scaled by the
±1 cm limit, and shrunk uniformly so its largest component is 1 (straight-line moves, no axis-wise
clipping that would bend the path into a tray wall). Yaw uses the ±10° rotation about the approach axis.

Phases (per env, batched): approach a hover point above the object while aligning the finger axis with
a cube face normal (smallest rotation modulo 90°) → descend → close → lift → carry above the
destination tray → lower → open. ``python -m maniskill_irb120.expert --episodes 100 --seed 0``
prints one JSON line with the success rate.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import dataclass

import gymnasium as gym
import torch
from mani_skill.utils.registration import REGISTERED_ENVS

from maniskill_irb120.envs.table_clearing import TRAY_INNER, TRAY_WALL_H, TableClearingIRB120Env

POS_LIMIT = 0.01  # m per action (pd_ee_delta_tool)
ROT_LIMIT = math.radians(10.0)  # rad per action
ENV_ID = "TableClearing-IRB120-v1"
# gripper_base collision box half extents across the approach axis: along the fingers / across them
GRIPPER_HALF_LONG, GRIPPER_HALF_SHORT = 0.032, 0.015

APPROACH, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT = range(8)
PHASE_NAMES = ["approach", "descend", "close", "lift", "carry", "lower", "release", "retreat"]


@dataclass
class ExpertConfig:
    hover: float = 0.06
    """TCP height above the object centre before descending (clears the 3 cm tray walls)"""
    grasp_offset: float = 0.005
    """TCP height above the object centre at the grasp: finger tips 4 mm below the centre, and the
    gripper body (17 mm above the TCP) 2 mm above the 3 cm tray walls for a 20 mm cube"""
    carry_height: float = 0.12
    """TCP height above the tray floor while lifting and carrying"""
    release_height: float = 0.006
    """object-centre height above its resting height when the gripper opens"""
    close_steps: int = 4
    release_steps: int = 3
    pos_tol: float = 0.002
    yaw_tol: float = math.radians(2.0)


class TableClearingExpert:
    """Batched phase machine; call :meth:`reset` after ``env.reset`` and :meth:`act` each step."""

    def __init__(self, env: TableClearingIRB120Env, config: ExpertConfig | None = None):
        self.env = env
        self.cfg = config or ExpertConfig()
        n, dev = env.num_envs, env.device
        self.phase = torch.zeros(n, dtype=torch.long, device=dev)
        self.counter = torch.zeros(n, dtype=torch.long, device=dev)
        self.grasp_xy = torch.zeros(n, 2, device=dev)

    def reset(self, env_idx: torch.Tensor | None = None):
        idx = slice(None) if env_idx is None else env_idx
        self.phase[idx] = APPROACH
        self.counter[idx] = 0

    def _yaw_error(self, tcp_rot: torch.Tensor) -> torch.Tensor:
        """Rotation about the TCP approach axis that aligns the finger axis with a cube face normal.

        The cube allows two finger directions (90° apart). The gripper body is 64 mm long along the
        finger axis but 30 mm across, so near a tray wall the direction that keeps the long side
        parallel to the wall wins; otherwise the smaller rotation does.
        """
        env = self.env
        obj_rot = env.obj.pose.to_transformation_matrix()[:, :3, :3]
        # the object's most horizontal axis is a side-face normal (any resting pose of a cube)
        axis_idx = obj_rot[:, 2, :].abs().argmin(dim=1)
        normal = torch.gather(obj_rot, 2, axis_idx.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(2)
        fingers = tcp_rot[:, :, 1]
        finger_ang = torch.atan2(fingers[:, 1], fingers[:, 0])
        e1 = torch.remainder(torch.atan2(normal[:, 1], normal[:, 0]) - finger_ang + math.pi / 4, math.pi / 2) - math.pi / 4
        e2 = e1 - torch.where(e1 >= 0, 1.0, -1.0) * (math.pi / 2)
        rel = (env.obj.pose.p[:, :2] - env.source_center[:, :2]).abs()
        wall_gap = TRAY_INNER / 2 - rel  # (N, 2) distance from the object centre to the nearest x / y wall

        def margin(e: torch.Tensor) -> torch.Tensor:
            ux, uy = torch.cos(finger_ang + e).abs(), torch.sin(finger_ang + e).abs()
            ext_x = GRIPPER_HALF_LONG * ux + GRIPPER_HALF_SHORT * uy
            ext_y = GRIPPER_HALF_LONG * uy + GRIPPER_HALF_SHORT * ux
            return torch.minimum(wall_gap[:, 0] - ext_x, wall_gap[:, 1] - ext_y)

        world_err = torch.where(margin(e2) > margin(e1) + 0.003, e2, e1)
        # a rotation by a about TCP x is a rotation by a * (x · ẑ) about world z
        return world_err * torch.sign(tcp_rot[:, 2, 0])

    def _targets(self, phase: torch.Tensor, tcp_p: torch.Tensor, yaw_err: torch.Tensor):
        """World-frame TCP target, yaw command (rad) and gripper command for each env's phase."""
        env, c = self.env, self.cfg
        n = env.num_envs
        obj_p = env.obj.pose.p
        h = env.object_half_size
        floor = env.source_center[:, 2]
        dest = env.dest_center
        target = tcp_p.clone()
        yaw = torch.zeros(n, device=env.device)
        gripper = -torch.ones(n, device=env.device)

        m = phase == APPROACH
        target[m, :2] = obj_p[m, :2]
        target[m, 2] = floor[m] + h + c.hover
        m = phase == DESCEND
        target[m, :2] = obj_p[m, :2]
        target[m, 2] = floor[m] + h + c.grasp_offset
        m = (phase == APPROACH) | (phase == DESCEND)
        yaw[m] = yaw_err[m]
        m = phase == LIFT
        target[m, :2] = self.grasp_xy[m]
        target[m, 2] = floor[m] + c.carry_height
        m = phase == CARRY
        target[m, :2] = dest[m, :2]
        target[m, 2] = floor[m] + c.carry_height
        m = phase == LOWER  # the TCP is grasp_offset above the held object's centre
        target[m, :2] = dest[m, :2]
        target[m, 2] = dest[m, 2] + h + c.release_height + c.grasp_offset
        m = phase == RETREAT
        target[m, 2] = dest[m, 2] + TRAY_WALL_H + 0.06
        gripper[(phase <= DESCEND) | (phase >= RELEASE)] = 1.0
        return target, yaw, gripper

    def act(self) -> torch.Tensor:
        """(N, 5) action for the current state; advances each env's phase first."""
        c = self.cfg
        tcp = self.env.agent.tcp_pose
        tcp_p = tcp.p
        tcp_rot = tcp.to_transformation_matrix()[:, :3, :3]
        yaw_err = self._yaw_error(tcp_rot)
        ph = self.phase

        target, _, _ = self._targets(ph, tcp_p, yaw_err)
        dist = torch.linalg.norm(target - tcp_p, dim=1)
        reached = dist < c.pos_tol
        aligned = yaw_err.abs() < c.yaw_tol
        nxt = ph.clone()
        nxt[(ph == APPROACH) & reached & aligned] = DESCEND
        nxt[(ph == DESCEND) & reached & aligned] = CLOSE
        nxt[(ph == CLOSE) & (self.counter >= c.close_steps)] = LIFT
        nxt[(ph == LIFT) & (dist < 0.005)] = CARRY
        nxt[(ph == CARRY) & (dist < 0.003)] = LOWER
        nxt[(ph == LOWER) & reached] = RELEASE
        nxt[(ph == RELEASE) & (self.counter >= c.release_steps)] = RETREAT
        entered = nxt != ph
        self.counter[entered] = 0
        self.grasp_xy[entered & (nxt == LIFT)] = tcp_p[entered & (nxt == LIFT), :2]
        self.counter[(nxt == CLOSE) | (nxt == RELEASE)] += 1
        self.phase = nxt

        target, yaw, gripper = self._targets(nxt, tcp_p, yaw_err)
        return self._to_action(target - tcp_p, yaw, gripper, tcp_rot)

    @staticmethod
    def _to_action(err: torch.Tensor, yaw: torch.Tensor, gripper: torch.Tensor, tcp_rot: torch.Tensor) -> torch.Tensor:
        local = (tcp_rot.transpose(1, 2) @ err.unsqueeze(2)).squeeze(2) / POS_LIMIT
        scale = local.abs().amax(dim=1, keepdim=True).clamp(min=1.0)
        local = local / scale
        rot = (yaw / ROT_LIMIT).clamp(-1, 1)
        return torch.cat([local, rot.unsqueeze(1), gripper.unsqueeze(1)], dim=1).clamp(-1, 1)


def make_env(obs_mode: str = "state", **kwargs) -> gym.Env:
    """The task with the expert's action space and the seed's reward (``dense``, not the env's default);
    ``kwargs`` go to the env (object size, mass, ...)."""
    kwargs.setdefault("reward_mode", "dense")
    return gym.make(ENV_ID, obs_mode=obs_mode, control_mode="pd_ee_delta_tool", **kwargs)


def _failure_reason(info: dict, expert: TableClearingExpert, truncated: bool) -> str:
    if bool(info["collided"][0]):
        return f"collision during {PHASE_NAMES[int(expert.phase[0])]}"
    if truncated:
        return f"timeout during {PHASE_NAMES[int(expert.phase[0])]}"
    return "unknown"


def run_expert(
    episodes: int = 100,
    seed: int = 0,
    obs_mode: str = "state",
    max_steps: int | None = None,
    record: bool = False,
    **env_kwargs,
) -> dict:
    """Roll the expert out for ``episodes`` single-env episodes seeded ``seed, seed+1, ...``.

    Returns success_rate, episodes, mean_steps (over all episodes), failure reason counts, steps/s
    and, with ``record``, per-episode actions and TCP positions (for determinism checks).
    """
    env = make_env(obs_mode, **env_kwargs)
    u: TableClearingIRB120Env = env.unwrapped
    limit = max_steps or REGISTERED_ENVS[ENV_ID].max_episode_steps
    expert = TableClearingExpert(u)
    successes, steps, reasons, drops, grasps, trajs = 0, [], Counter(), 0, 0, []
    total_steps, t0 = 0, time.perf_counter()
    for ep in range(episodes):
        env.reset(seed=seed + ep)
        expert.reset()
        actions, tcps = [], []
        info, truncated = {}, False
        for t in range(limit):
            a = expert.act()
            if record:
                actions.append(a[0].cpu().clone())
                tcps.append(u.agent.tcp_pose.p[0].cpu().clone())
            _, _, term, trunc, info = env.step(a)
            total_steps += 1
            drops += int(info["dropped"][0])
            grasps += int(info["r_grasp"][0] > 0)
            if bool(term[0]) or bool(trunc[0]):
                truncated = bool(trunc[0]) and not bool(term[0])
                break
        else:
            truncated = True
        ok = bool(info["success"][0])
        successes += ok
        steps.append(t + 1)
        if not ok:
            reasons[_failure_reason(info, expert, truncated)] += 1
        if record:
            trajs.append(dict(actions=torch.stack(actions), tcp=torch.stack(tcps), success=ok))
    elapsed = time.perf_counter() - t0
    env.close()
    out = dict(
        success_rate=successes / episodes,
        episodes=episodes,
        seed=seed,
        mean_steps=sum(steps) / episodes,
        max_steps=max(steps),
        failures=dict(reasons),
        grasp_events=grasps,
        drop_events=drops,
        steps_per_s=total_steps / elapsed,
        wall_s=elapsed,
    )
    if record:
        out["trajectories"] = trajs
    return out


@dataclass
class Args:
    episodes: int = 100
    """number of seeded episodes (seeds seed .. seed+episodes-1)"""
    seed: int = 0
    obs_mode: str = "state"
    """observation mode; the expert reads privileged state, so 'state' is fastest"""


def main(args: Args) -> None:
    result = run_expert(args.episodes, args.seed, obs_mode=args.obs_mode)
    print(json.dumps(result))


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
