"""Teleoperating a task in simulation and recording the episodes as ManiSkill trajectories (``RecordEpisode``:
h5 + json, the env's state every step, the task's success), which ManiSkill's replay tool replays, and, recorded
in ``pd_joint_pos``, converts to its other control modes.

The device drives ``pd_ee_delta_tool``: its x/y/z along the tool's axes or the world's (``frame``), its yaw about
the tool's approach axis, the gripper toggled. In ``pd_joint_pos`` each such tool action is recorded as the joint
targets it commands, through the same IK path the expert's ``pd_joint_pos`` demos take
(:class:`~maniskill_irb120.experts.demos.JointTargets`). The env steps at its control rate whether or not a key
is down (a human needs the pauses as much as the moves); an episode that ends (success, failure or time limit)
waits for save, reset or discard. Episodes are kept only when saved.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import gymnasium as gym
import torch
from mani_skill.utils.wrappers.record import RecordEpisode

import maniskill_irb120  # noqa: F401
from maniskill_irb120.action import tcp_rotation, world_to_tool
from maniskill_irb120.envs.table_clearing import ENV_ID as DEFAULT_ENV_ID
from maniskill_irb120.experts.demos import CONTROL_MODES, JointTargets, name_env_in_json
from maniskill_irb120.teleop.devices import Command, Device

FRAMES = ("tool", "world")
VIEWS = ("auto", "window", "none")


@dataclass(frozen=True)
class TeleopConfig:
    env_id: str = DEFAULT_ENV_ID
    """the task (a registered env id)"""
    frame: Literal["tool", "world"] = "world"
    """axes the device's x/y/z move along: the world's, or the TCP's (tool; x is the approach axis)"""
    control_mode: str = "pd_ee_delta_tool"
    """what is recorded: the tool actions, or (pd_joint_pos) the joint targets they command"""
    out_dir: Path = Path("demos")
    """where <name>.h5 and <name>.json go"""
    name: str = "teleop"
    """the trajectory file's name"""
    seed: int = 0
    """the first episode's seed; each saved or discarded episode moves on to the next"""
    speed: float = 0.5
    """the fraction of the action space's full step (1 cm, 10 deg per step) a full deflection commands"""
    max_episode_steps: int = 1200
    """an episode's time limit (a minute at 20 Hz: a person needs longer than the scripted expert)"""
    view: Literal["auto", "window", "none"] = "auto"
    """show the overview and the hand camera in a window: auto does where a display exists"""
    realtime: bool = True
    """step at the env's control rate (20 Hz); False: as fast as the device is polled"""

    def __post_init__(self):
        if self.frame not in FRAMES:
            raise ValueError(f"frame={self.frame!r}: use one of {FRAMES}")
        if self.control_mode not in CONTROL_MODES:
            raise ValueError(f"control_mode={self.control_mode!r} is not one of {CONTROL_MODES}")
        if not 0 < self.speed <= 1:
            raise ValueError(f"speed must be in (0, 1], got {self.speed}")
        if self.max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {self.max_episode_steps}")
        if self.view not in VIEWS:
            raise ValueError(f"view={self.view!r}: use one of {VIEWS}")


def display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class Viewer:
    """The env's "all" render (the overview camera beside the hand camera) in an OpenCV window."""

    def __init__(self, title: str):
        import cv2

        self.cv2, self.title = cv2, title

    def show(self, frame: torch.Tensor) -> None:
        self.cv2.imshow(self.title, frame[0].cpu().numpy()[..., ::-1])  # RGB -> OpenCV's BGR
        self.cv2.waitKey(1)

    def close(self) -> None:
        self.cv2.destroyWindow(self.title)


def tool_action(cmd: Command, gripper: float, speed: float) -> torch.Tensor:
    """The (1, 5) normalised action of a command, in the command's own frame."""
    return torch.tensor([[*(v * speed for v in cmd.translation), cmd.yaw * speed, gripper]], dtype=torch.float32)


class Session:
    """One env, one device, one trajectory file. ``step()`` is one control period; ``run()`` paces it."""

    def __init__(self, cfg: TeleopConfig, device: Device, say=print):
        self.cfg, self.device, self.say = cfg, device, say
        view = cfg.view == "window" or (cfg.view == "auto" and display_available())
        env = gym.make(
            cfg.env_id,
            obs_mode="none",
            control_mode=cfg.control_mode,
            reward_mode="dense",
            render_mode="all" if view else None,
            max_episode_steps=cfg.max_episode_steps,
        )
        self.joint_targets = JointTargets(env) if cfg.control_mode == "pd_joint_pos" else None
        self.env = RecordEpisode(
            env,
            output_dir=str(cfg.out_dir),
            trajectory_name=cfg.name,
            save_video=False,
            save_on_reset=False,
            record_env_state=True,
            source_type="teleoperation",
            source_desc=f"maniskill_irb120 teleop, {cfg.frame} frame",
        )
        self.viewer = None
        if view:
            try:
                self.viewer = Viewer(f"{cfg.env_id} (overview | hand camera)")
            except ImportError:
                say("no window: OpenCV is not installed (pip install opencv-python)")
        self.h5, self.json = Path(cfg.out_dir) / f"{cfg.name}.h5", Path(cfg.out_dir) / f"{cfg.name}.json"
        self.seed, self.saved, self.dropped = cfg.seed, [], 0
        self.new_episode(cfg.seed)

    def new_episode(self, seed: int) -> None:
        self.env.reset(seed=seed)
        self.seed, self.steps, self.done, self.gripper = seed, 0, False, 1.0
        self.success = False

    def end_episode(self, save: bool, next_seed: int) -> None:
        if save and self.steps:
            self.env.flush_trajectory(save=True)
            name_env_in_json(self.json, self.cfg.env_id)
            self.saved.append(dict(seed=self.seed, steps=self.steps, success=self.success))
            self.say(f"saved episode {len(self.saved)} (seed {self.seed}, {self.steps} steps, success {self.success})")
        else:
            self.env.flush_trajectory(save=False)
            self.dropped += bool(self.steps)
        self.new_episode(next_seed)

    def action(self, cmd: Command) -> torch.Tensor:
        a = tool_action(cmd, self.gripper, self.cfg.speed)
        agent = self.env.unwrapped.agent
        if self.cfg.frame == "world":
            a = world_to_tool(a, tcp_rotation(agent.tcp_pose.raw_pose.cpu()).to(a.dtype))
        if self.joint_targets is not None:
            a = self.joint_targets(a.to(self.env.unwrapped.device))
        return a

    def step(self) -> bool:
        """Poll the device and act on it; False once it quits."""
        cmd = self.device.poll()
        if cmd.quit:
            return False
        if cmd.save or cmd.discard or cmd.reset:
            if cmd.save and not self.steps:
                self.say("nothing to save yet")
                return True
            self.end_episode(save=cmd.save, next_seed=self.seed if cmd.reset and not cmd.save else self.seed + 1)
            self.say(f"seed {self.seed}")
            return True
        if self.done:
            return True
        if cmd.gripper_toggle:
            self.gripper = -self.gripper
        _, _, term, trunc, info = self.env.step(self.action(cmd))
        self.steps += 1
        self.success = bool(info["success"][0])
        if bool(term[0]) or bool(trunc[0]):
            self.done = True
            why = "success" if self.success else ("failed" if bool(info["fail"][0]) else "time limit")
            self.say(f"episode over ({why}): Enter saves, Backspace resets, n discards")
        if self.viewer is not None and self.steps % 2 == 0:
            self.viewer.show(self.env.render())
        return True

    def run(self) -> dict:
        """Step at the control rate until the device quits; the episode in progress is dropped."""
        period = 1.0 / self.env.unwrapped.control_freq
        c = self.cfg
        self.say(f"ready: {c.env_id}, seed {self.seed}, {c.frame} frame, recording {c.control_mode} to {self.h5}")
        t_next = time.monotonic()
        try:
            while self.step():
                if self.cfg.realtime:
                    t_next = max(t_next + period, time.monotonic() - period)
                    time.sleep(max(0.0, t_next - time.monotonic()))
        finally:
            self.close()
        return self.result()

    def result(self) -> dict:
        return dict(
            env_id=self.cfg.env_id,
            control_mode=self.cfg.control_mode,
            frame=self.cfg.frame,
            h5=str(self.h5),
            json=str(self.json),
            episodes_saved=len(self.saved),
            successes=sum(e["success"] for e in self.saved),
            episodes_dropped=self.dropped,
        )

    def close(self) -> None:
        if self.env is None:
            return
        if self.viewer is not None:
            self.viewer.close()
        self.env.flush_trajectory(save=False)
        self.env.close()
        self.env = None
        if self.saved:
            name_env_in_json(self.json, self.cfg.env_id)


def teleop(cfg: TeleopConfig, device: Device, say=print) -> dict:
    """Run a teleoperation session; returns where the episodes went and how many were saved."""
    session = Session(cfg, device, say)
    return session.run()
