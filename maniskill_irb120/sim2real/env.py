"""``IRB120Sim2RealEnv``: ManiSkill's ``Sim2RealEnv`` for the IRB 120 behind our RAPID server.

What it changes in ManiSkill's class, and why:

- ``tool_delta`` (default): ``_step_action`` sends the env's action itself (the controller's ``RelTool`` does
  the rest), instead of the sim controller's IK joint targets; ``joint_target`` keeps ManiSkill's path.
- Timing: the command goes out at the start of a control period and the robot is read at its end, so the
  observation a step returns shows that step's motion (ManiSkill's class sleeps before sending). With
  ``step_end="arrived"`` (default) the step ends only once the controller reports the robot standing at the step's
  target: the sim's drives have settled by the end of every period (joint speeds ~1e-3 rad/s), while the IRC5 with
  its acceleration ramps needs ~58 ms for a full 10 mm step. Read at 50 ms, the robot is still moving (joint speeds
  up to 2 rad/s where the sim shows none), and the next step, taken relative to where the robot is, loses the rest
  of the one before: open loop, the TCP fell 45 mm behind the sim's within 25 steps. ``"period"`` keeps the fixed
  clock (the robot's own timing, for studying that gap).
- ``get_info``: Sim2RealEnv reports only ``elapsed_steps``. Ours adds what the tasks' observations need
  (``grasped``, the TCP pose) and, with a digital ``world`` (the emulator's twin), the twin's evaluation:
  success, grasp, drop, collisions. A real robot's success comes from the operator (``sim2real.eval``).
- ``reset`` restarts the step count (ManiSkill's never does: its time limit then cuts later episodes short).
- The task's observations read ``step_state`` and ``tcp_pose`` (envs/base.py), which ``get_info`` fills here:
  the TCP pose is the FK of the joints the robot reported, the object poses are the world's
  ``privileged_state()`` (the twin's task declares them; no list of names here). A real robot has no perception,
  so state observations are refused with that reason instead of silently reading the sim's stale poses.
- A private attribute of the task (a ``_name`` this class lacks) is an ``AttributeError`` naming it: ManiSkill's
  ``__getattr__`` would hand out the idle sim's value (a reset-time pose all episode long).

    env = IRB120Sim2RealEnv(sim_env, agent, world=twin)   # agent: IRB120RealAgent
    obs, info = env.reset(seed=0)
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.envs.sim2real_env import Sim2RealEnv

from maniskill_irb120.abb.client import ControllerRefused
from maniskill_irb120.abb.envelope import EnvelopeError
from maniskill_irb120.abb.protocol import Status
from maniskill_irb120.envs.contract import EnvContractMixin
from maniskill_irb120.sim2real.agent import IRB120RealAgent

ON_REFUSAL = ("raise", "hold")
STEP_ENDS = ("arrived", "period")
# ManiSkill's own private state that its BaseEnv methods (run with this env as ``self``) read from the sim
_SIM_PRIVATE = frozenset({"_sensors", "_sensor_configs", "_hidden_objects", "_human_render_cameras"})


class _Unperceived(dict):
    """The step state of a robot without a world: the TCP pose only; an object pose is refused by name."""

    def __missing__(self, key: str):
        raise RuntimeError(
            f"{key!r} is privileged object state: a real robot has no perception of it, so state "
            "observations cannot be formed; use obs_mode='rgbd' (or run on the emulator's digital twin)"
        )


class IRB120Sim2RealEnv(Sim2RealEnv):
    def __init__(
        self,
        sim_env,
        agent: IRB120RealAgent,
        world=None,
        on_refusal: str = "raise",
        step_end: str = "arrived",
        arrive_timeout_s: float = 0.5,
        **kwargs,
    ):
        """``sim_env``: the task on ``physx_cpu`` in ``pd_ee_delta_tool`` (tool_delta) or any pd_*_pos mode
        (joint_target). ``world``: a ``DigitalTwin`` on the emulator, or None on a real robot. ``on_refusal``:
        a command the envelope or the controller refuses raises (``"raise"``), or the robot holds for that
        period and the refusal is recorded in ``refusals`` and ``info["refused"]`` (``"hold"``, for evaluation).
        ``step_end``: ``"arrived"`` (a step ends when the robot stands at its target, at the earliest after one
        control period, at the latest ``arrive_timeout_s`` after the command: a later step is counted in
        ``late_steps`` and ``info["late"]``) or ``"period"`` (every step one control period)."""
        if on_refusal not in ON_REFUSAL:
            raise ValueError(f"on_refusal={on_refusal!r}: use one of {ON_REFUSAL}")
        if step_end not in STEP_ENDS:
            raise ValueError(f"step_end={step_end!r}: use one of {STEP_ENDS}")
        if not arrive_timeout_s > 0:
            raise ValueError(f"arrive_timeout_s={arrive_timeout_s}: must be > 0 seconds")
        mode = sim_env.unwrapped.control_mode
        if agent.command_mode == "tool_delta" and mode != "pd_ee_delta_tool":
            raise ValueError(f"command_mode='tool_delta' sends pd_ee_delta_tool actions; the sim env uses {mode!r}")
        if agent.abb is None:
            agent.start()  # connect (and start the camera) before ManiSkill's first reset needs the robot
        self.world, self.on_refusal = world, on_refusal
        self.step_end, self.arrive_timeout_s = step_end, arrive_timeout_s
        self.refusals: list[str] = []
        self.late_steps = 0
        self._refused = self._late = False
        self._world_info: dict = {}
        self.step_state: dict[str, torch.Tensor] = {}
        kwargs.setdefault("real_reset_function", _reset_both_sides)
        kwargs.setdefault("sensor_data_preprocessing_function", _check_sensor_frames(sim_env))
        super().__init__(sim_env, agent, **kwargs)

    def reset(self, seed=None, options=None):
        """ManiSkill 3.0.1's Sim2RealEnv never resets its step count, so its TimeLimit truncated every episode
        after the first 250 steps in all; each episode counts from 0 here."""
        self._elapsed_steps = torch.zeros_like(self._elapsed_steps)
        return super().reset(seed=seed, options=options)

    # ------------------------------------------------------------------ acting
    def _step_action(self, action):
        self._refused = False
        try:
            if self.last_control_time is None:
                self.last_control_time = time.perf_counter()
            if self.agent.command_mode == "joint_target":
                # ManiSkill's path without its sleep before sending: the sim controller's IK, then its drive
                # targets as one MoveAbsJ
                self.base_sim_env.agent.set_action(torch.as_tensor(action, dtype=torch.float32).reshape(1, -1))
                self.agent.set_target_qpos(self.agent.controller.articulation.drive_targets)
            else:
                a = torch.as_tensor(action).detach().cpu().reshape(-1).numpy()
                if a.shape != self._orig_single_action_space.shape or not np.all(np.isfinite(a)):
                    raise ValueError(f"action must be 5 finite numbers, got {a}")
                self.agent.send_tool_action(np.clip(a, -1.0, 1.0))
        except (EnvelopeError, ControllerRefused) as e:
            if self.on_refusal == "raise":
                raise
            self.refusals.append(e.limit if isinstance(e, EnvelopeError) else e.state.error.name)
            self._refused = True
        # the rest of the period: the robot moves; then read it (and the world follows it)
        sent = self.last_control_time
        left = self.control_dt - (time.perf_counter() - sent)
        if left > 0:
            time.sleep(left)
        state = self.agent.refresh()
        self._late = False
        if self.step_end == "arrived":
            while state.status == Status.MOVING:
                if time.perf_counter() - sent > self.arrive_timeout_s:
                    self._late = True
                    self.late_steps += 1
                    break
                state = self.agent.refresh()
        self.last_control_time = time.perf_counter()
        if self.world is not None:
            self._world_info = self.world.follow()
        return action

    # ------------------------------------------------------------------ what the tasks' observations read
    @property
    def tcp_pose(self) -> torch.Tensor:
        """(1, 7) FK of the joints the robot reported at the end of this step (the task's ``tcp_pose``)."""
        return self.step_state["tcp_pose"]

    def get_info(self) -> dict:
        """The task's step state from the robot (FK) and the world, then the info (the world's evaluation)."""
        sim = self.base_sim_env
        sim.agent.robot.set_qpos(self.agent.get_qpos().to(sim.device))
        tcp = sim.agent.tcp_pose.raw_pose.clone()
        if self.world is not None:
            self.step_state = {**self.world.privileged_state(), "tcp_pose": tcp}
        else:
            self.step_state = _Unperceived(tcp_pose=tcp)
        info = dict(
            elapsed_steps=self._elapsed_steps, refused=torch.tensor([self._refused]), late=torch.tensor([self._late])
        )
        if self.world is not None:
            info.update({k: v for k, v in self._world_info.items() if k != "elapsed_steps"})
        else:
            closed = torch.tensor([not self.agent.state.gripper_open])
            info["grasped"] = closed  # pneumatic gripper, no sensing: closed is the best a real robot tells
        return info

    def _get_obs_state_dict(self, info: dict) -> dict:
        """ManiSkill's class leaves this to ``__getattr__``, i.e. to the *sim* env's state: the real side's obs
        would silently be the simulation's. Built here from the real agent and the world."""
        return BaseEnv._get_obs_state_dict(self, info)

    def _get_obs_extra(self, info: dict) -> dict:
        # the task's own, without ManiSkill's wrapper that turns any error into a print and exit(-1)
        return type(self.base_sim_env)._get_obs_extra(self, info)

    def get_reward(self, obs, action, info):
        """The world's reward on the twin (it knows where the object is); none on a real robot."""
        return self.world.reward if self.world is not None else torch.zeros(1)

    def __getattr__(self, name: str) -> Any:
        """Public names (the task's constants: tray centres, ``object_half_size``, ``state_observations``) and
        ManiSkill's own machinery come from the sim env, as in ManiSkill's class; a task's private attribute does
        not: on the sim it is the sim's state, never the robot's."""
        if name.startswith("_") and not (
            name in _SIM_PRIVATE or hasattr(BaseEnv, name) or hasattr(EnvContractMixin, name) or name.startswith("__")
        ):
            raise AttributeError(
                f"{type(self).__name__} has no {name!r}: the task's private attribute would be the idle sim's "
                "state, not the robot's. Tasks expose what the real side reads through privileged_state(), "
                "step_state, tcp_pose and target_object (envs/base.py)."
            )
        return super().__getattr__(name)


def _reset_both_sides(env: IRB120Sim2RealEnv, seed=None, options=None) -> None:
    """The sim episode ``seed``; the world laid out for the same seed (the twin; a person on a real robot); the
    robot moved slowly to the sim's start pose."""
    env.sim_env.reset(seed=seed, options=options)
    if env.world is not None:
        start = env.world.reset(seed=seed)
        env._world_info = env.world.info
    else:
        start = env.base_sim_env.agent.robot.get_qpos()[0].cpu().numpy()
    env.agent.reset(start)
    if env.world is None:  # a person lays the scene out, then says so (ManiSkill's default does the same)
        input(f"Lay out the scene for episode seed {seed} (see the sim's first frame), then press Enter ")
    env.last_control_time = None


def _check_sensor_frames(sim_env):
    """The cameras return the sim's format already (``to_sim_frame``); say so if one does not, rather than let
    ManiSkill's default resize drop the depth channel."""

    def check(data: dict) -> dict:
        configs = sim_env.unwrapped._sensor_configs
        for name, frames in data.items():
            cfg = configs[name]
            for key, dtype, ch in (("rgb", torch.uint8, 3), ("depth", torch.int16, 1)):
                if key in frames:
                    want = (1, cfg.height, cfg.width, ch)
                    got = frames[key]
                    if tuple(got.shape) != want or got.dtype != dtype:
                        raise ValueError(
                            f"{name}.{key}: got {got.dtype} {tuple(got.shape)}, the sim gives {dtype} {want}"
                        )
        return data

    return check
