"""Expert demonstrations in ManiSkill's trajectory format (h5 + json), via ManiSkill's RecordEpisode.

The json names the env as ``maniskill_irb120:<env id>``, so ManiSkill's own replay tool finds it in a
fresh interpreter with no import of ours::

    python -m mani_skill.trajectory.replay_trajectory --traj-path demos/expert.h5 --use-env-states

Recorded in ``pd_joint_pos`` (``control_mode="pd_joint_pos"``), the replay tool also converts them to the other
joint and end-effector modes (``-c pd_joint_delta_pos``, ``-c pd_ee_delta_pose``): ManiSkill converts only
from ``pd_joint_pos`` and ``pd_joint_delta_pos``, never from ``pd_ee_delta_tool``.
"""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import torch
from mani_skill.utils.wrappers.record import RecordEpisode

import maniskill_irb120  # noqa: F401
from maniskill_irb120.envs.table_clearing import ENV_ID as DEFAULT_ENV_ID
from maniskill_irb120.errors import UsageError, nearest
from maniskill_irb120.experts import expert_for
from maniskill_irb120.experts.pick_place import PickPlaceExpert
from maniskill_irb120.experts.rollout import run_episode
from maniskill_irb120.robot.kinematics import ArmIK, DLSParams, SerialChain

CONTROL_MODES = ("pd_ee_delta_tool", "pd_joint_pos")
"""The modes demos are recorded in: the expert's own, or the joint targets its tool actions command."""


class JointTargets:
    """Tool actions → the ``pd_joint_pos`` actions that command the same motion on an env in that mode, i.e. what
    ``pd_ee_delta_tool``'s controller does with them: the arm's IK target for ``T(measured joints) · Δ`` (the same
    :class:`ArmIK`, limits and joint-speed check) or, where that is unreachable, the last joint target, followed
    by the action's gripper value. (N, 5) in, (N, 7) out. Whatever decides the tool actions (the scripted expert,
    a teleoperator) records joint targets through this one path."""

    def __init__(self, env: gym.Env):
        self.env = env.unwrapped
        cfg = self.env.agent._controller_configs["pd_ee_delta_tool"]["arm"]
        chain = SerialChain(cfg.urdf_path, cfg.ee_link, device=self.env.device)
        dls = DLSParams(cfg.ik_iterations, cfg.ik_damping, cfg.ik_pos_tol, cfg.ik_rot_tol)
        self.ik = ArmIK(chain, cfg.ik_solver, dls, max_joint_step=chain.velocity / self.env.control_freq)
        self.limits = torch.tensor([cfg.pos_limit] * 3 + [cfg.rot_limit], device=self.env.device)

    def __call__(self, action: torch.Tensor) -> torch.Tensor:
        arm = self.env.agent.arm_controller
        tool = action[:, :4].clamp(-1.0, 1.0) * self.limits.to(action.dtype)
        q, ok, _ = self.ik.tool_step(arm.qpos, tool)
        target = torch.where(ok[:, None], q.to(arm._target_qpos.dtype), arm._target_qpos)
        return torch.cat([target, action[:, 4:].to(target.dtype)], 1)


class JointTargetExpert:
    """The task's tool-frame expert acting on an env in ``pd_joint_pos``: each step it still decides a tool
    action from the state, and returns the joint-position action that commands the same motion
    (:class:`JointTargets`). (N, 7) actions."""

    def __init__(self, env: gym.Env, expert: PickPlaceExpert):
        self.expert, self.targets = expert, JointTargets(env)

    def reset(self) -> None:
        self.expert.reset()

    @property
    def phase(self) -> torch.Tensor:
        return self.expert.phase

    def act(self) -> torch.Tensor:
        return self.targets(self.expert.act())


def name_env_in_json(json_path: Path, env_id: str) -> None:
    """Name the env ``maniskill_irb120:<env id>`` in a RecordEpisode json, so ManiSkill's replay tool imports this
    package in a fresh interpreter (RecordEpisode writes the bare id)."""
    meta = json.loads(Path(json_path).read_text())
    meta["env_info"]["env_id"] = f"maniskill_irb120:{env_id}"
    Path(json_path).write_text(json.dumps(meta, indent=2))


def collect_demos(
    episodes: int = 10,
    seed: int = 0,
    out_dir: Path = Path("demos"),
    name: str = "expert",
    obs_mode: str = "none",
    only_success: bool = True,
    save_video: bool = False,
    env_id: str = DEFAULT_ENV_ID,
    control_mode: str = "pd_ee_delta_tool",
    **env_kwargs,
) -> dict:
    """Roll out the task's expert for seeds ``seed..seed+episodes-1`` and record each episode.

    ``only_success`` drops failed episodes from the file (ManiSkill's convention for demo sets). The
    recorded rewards are the task's ``dense`` ones. ``control_mode``: the actions recorded, the expert's tool
    actions (``pd_ee_delta_tool``) or the joint targets they command (``pd_joint_pos``, see
    :class:`JointTargetExpert`), the mode ManiSkill's replay tool converts to others.
    Returns the paths and counts; raises if nothing was kept.
    """
    if episodes < 1:
        raise UsageError(f"--episodes {episodes}: give a whole number >= 1")
    if control_mode not in CONTROL_MODES:
        hint = nearest(control_mode, CONTROL_MODES)
        raise UsageError(f"--control-mode {control_mode!r}{hint}: use one of {', '.join(CONTROL_MODES)}")
    out_dir = Path(out_dir)
    env = gym.make(
        env_id,
        obs_mode=obs_mode,
        control_mode=control_mode,
        reward_mode="dense",
        render_mode="rgb_array" if save_video else None,
        **env_kwargs,
    )
    expert = expert_for(env)
    if control_mode == "pd_joint_pos":
        expert = JointTargetExpert(env, expert)
    env = RecordEpisode(
        env,
        output_dir=str(out_dir),
        trajectory_name=name,
        save_video=save_video,
        save_on_reset=False,
        record_env_state=True,
        video_fps=20,
        source_type="motion_planning",
        source_desc="maniskill_irb120 scripted expert",
    )
    kept = 0
    for ep in range(episodes):
        keep = run_episode(env, expert, seed + ep).success or not only_success
        env.flush_trajectory(save=keep)
        if save_video:
            env.flush_video(save=keep)
        kept += keep
    env.close()
    h5, js = out_dir / f"{name}.h5", out_dir / f"{name}.json"
    if kept == 0:
        raise RuntimeError(f"no successful episode among {episodes}; nothing recorded")
    name_env_in_json(js, env_id)
    return dict(
        env_id=env_id,
        control_mode=control_mode,
        h5=str(h5),
        json=str(js),
        episodes_recorded=kept,
        episodes_tried=episodes,
    )
