"""The digital twin: the "real world" behind the controller emulator.

A second env of the same task whose robot follows the emulated controller's joints (its joint drives track
them, so the fingers push the object as a real arm would, instead of teleporting through it), whose object is
simulated, which renders the hand camera the real agent returns (``TwinCamera``) and which scores the episode
(``evaluate()``). With a ``shift`` (``Randomization``: camera mount, field of view, lighting, colours, depth
noise, object size/mass/friction) it differs from the sim a policy was trained in; command latency is the
emulator's (``ControllerEmulator(latency_ms=...)``), since the twin only sees what the controller did.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

import maniskill_irb120  # noqa: F401  (registers the tasks)
from maniskill_irb120.abb.emulator.controller import ControllerEmulator
from maniskill_irb120.sim2real.cameras import TwinCamera

GRIPPER_SIGNAL = "doGripperOpen"


class DigitalTwin:
    """``env_id`` with ``control_mode="pd_joint_pos"``, driven from ``emulator``'s robot. ``env_kwargs`` go to the
    task as they would to the training sim (``object_shape``, ``randomization``, ...)."""

    def __init__(self, env_id: str, emulator: ControllerEmulator, obs_mode: str = "rgbd", **env_kwargs):
        self.emulator = emulator
        self.env = gym.make(
            env_id, obs_mode=obs_mode, control_mode="pd_joint_pos", sim_backend="physx_cpu", **env_kwargs
        )
        self.u = self.env.unwrapped
        self.camera = TwinCamera(self)
        self.obs: dict | None = None
        self.info: dict = {}
        self.reward = torch.zeros(1)

    def reset(self, seed: int | None = None) -> np.ndarray:
        """A fresh scene as an operator would lay it out for episode ``seed``; the robot's start pose (8,)."""
        self.obs, self.info = self.env.reset(seed=seed)
        self.info = dict(self.u.evaluate())
        return self.u.agent.robot.get_qpos()[0].cpu().numpy()

    def follow(self) -> dict:
        """One control period of the world: the twin's drives track the emulated robot's joints and gripper
        now; returns the task's evaluation (success, grasped, collisions, ...)."""
        q = np.radians(self.emulator.robot.joints())
        grip = 1.0 if self.emulator.signals.get(GRIPPER_SIGNAL, 1) else -1.0
        self.obs, self.reward, _, _, info = self.env.step(torch.as_tensor(np.r_[q, grip], dtype=torch.float32)[None])
        self.info = info
        return info

    def finger_qpos(self) -> np.ndarray:
        return self.u.agent.robot.get_qpos()[0, 6:].cpu().numpy()

    def privileged_state(self) -> dict:
        """The object poses the task declares (``privileged_state()``, envs/base.py): what the real side's state
        observations read, as a perception system would report them."""
        return {k: v.clone() for k, v in self.u.privileged_state().items()}

    def close(self) -> None:
        self.env.close()
