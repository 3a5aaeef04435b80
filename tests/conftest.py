"""Shared fixtures of the test suite.

``bench``: a bare scene with the robot on the floor and one 20 mm cube under the rest pose's TCP (the grasp
scenario the agent's own tests use), as ``bench.make(...)``, with ``bench.OPEN`` (a hold-still action with the
gripper open), ``bench.tcp_matrix(env)``, ``bench.CUBE_HALF`` and ``bench.REPO`` (the repository root).
``make_task``: ``make_task(env_id, **kwargs)`` builds a task (``obs_mode="state"`` unless given) and closes it
after the test.
``readme_snippet``: ``readme_snippet(name)`` is the python block marked ``<!-- snippet "name" ... -->`` in
README.md or a docs page (``docs/*.md``), so tests run the pages themselves.
``slow_clock``: ``slow_clock(robot, factor=3)`` runs an emulator robot model's clock ``factor`` times slower than
the wall clock, for tests that read the robot mid-motion; the robot finishes its motion and gets its clock back after
the test.
``terminate_group``: ``terminate_group(argv, started)`` runs a command in its own process group, sends the group
SIGTERM once ``started()`` is true, and returns the exit status and the stderr lines that are not library warnings
(``sigint_ignored=True``: started as a script's ``cmd &`` starts it).
``repo_script``: ``repo_script(name)`` is ``scripts/<name>.py`` run afresh as the module ``name`` (registered in
``sys.modules``, where a dataclass of its CLI looks its module up).
"""

from __future__ import annotations

import gc
import importlib.util
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import sapien
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.building import actors
from mani_skill.utils.building.ground import build_ground
from mani_skill.utils.registration import REGISTERED_ENVS, register_env

import maniskill_irb120  # noqa: F401

REPO = Path(__file__).resolve().parents[1]


def pytest_collection_finish(session):
    """ManiSkill's env clears its scene with a full ``gc.collect()`` at every reconfigure and close
    (``BaseEnv._clear``), and with torch, SAPIEN and the RL libraries imported each pass walks hundreds of thousands
    of objects: a fifth of a selection test's time went there. What collection imported lives as long as the
    worker, so it is moved out of the collector's reach (``gc.freeze``); what the tests build is collected as before."""
    gc.collect()
    gc.freeze()


@pytest.fixture(autouse=True)
def _one_torch_thread_per_xdist_worker():
    """Under pytest-xdist (``-n 2`` on CI's 2 cores) each worker is one of as many processes as cores, and torch's
    default of a thread per core in each oversubscribes them: its spinning threads made a small update several
    times slower on 2 cores. Each test starts on one torch thread; a test (or trainer) that sets its own count
    keeps it, and the count is put back after the test. Run alone (``-n 0``), tests keep torch's default."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def _torch_determinism_put_back():
    """Ray RLlib seeds torch on a CPU-only build with ``torch.use_deterministic_algorithms(True)``
    (``ray.rllib.utils.torch_utils.set_torch_seed``), for the whole process, and under it ``torch.empty`` fills the
    memory it returns: a camera DAgger run later in the same pytest worker then made its whole 300,000-row dataset
    resident, 11.7 GB, and a CI worker was OOM-killed. Each test gets the setting back as it found it."""
    before = torch.are_deterministic_algorithms_enabled()
    try:
        yield
    finally:
        if torch.are_deterministic_algorithms_enabled() != before:
            torch.use_deterministic_algorithms(before)


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
            self.cube = actors.build_cube(
                self.scene,
                half_size=CUBE_HALF,
                color=[1, 0, 0, 1],
                name="cube",
                initial_pose=sapien.Pose(p=[0.35, 0, CUBE_HALF]),
            )

        def _initialize_episode(self, env_idx, options):
            qpos = torch.as_tensor(self.agent.keyframes["rest"].qpos, dtype=torch.float32)
            self.agent.reset(qpos.expand(len(env_idx), -1))
            self.cube.set_pose(sapien.Pose(p=[0.35, 0, CUBE_HALF]))

        def evaluate(self):
            return {}

        def _get_obs_extra(self, info):
            return {}


def _make(obs_mode="none", control_mode="pd_ee_delta_tool", **kw):
    env = gym.make("IRB120CubeBench-test", obs_mode=obs_mode, control_mode=control_mode, reward_mode="none", **kw)
    env.reset(seed=0)
    return env


OPEN = np.array([0, 0, 0, 0, 1], dtype=np.float32)


def _tcp_matrix(env) -> torch.Tensor:
    return env.unwrapped.agent.tcp_pose.to_transformation_matrix()[0].double()


@pytest.fixture
def bench() -> SimpleNamespace:
    return SimpleNamespace(make=_make, OPEN=OPEN, tcp_matrix=_tcp_matrix, CUBE_HALF=CUBE_HALF, REPO=REPO)


@pytest.fixture
def make_task():
    """``make_task(env_id, **gym_make_kwargs)``: a task env (obs_mode "state" unless given), closed after the test."""
    made = []

    def make(env_id: str, **kw):
        kw.setdefault("obs_mode", "state")
        env = gym.make(env_id, **kw)
        made.append(env)
        return env

    yield make
    for env in made:
        env.close()


def _readme_snippet(name: str) -> str:
    """The fenced python block right after the marker ``<!-- snippet "name" ... -->`` in README.md or a docs page."""
    for page in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        m = re.search(
            rf'<!-- (?:README )?snippet "{re.escape(name)}".*?-->\s*```python\n(.*?)```', page.read_text(), re.S
        )
        if m:
            return m.group(1)
    raise AssertionError(f"neither README.md nor docs/*.md has a snippet marked {name!r}")


@pytest.fixture
def readme_snippet():
    """``readme_snippet(name)``: the python block marked with that name in the README or the docs, so the tests run
    the pages themselves."""
    return _readme_snippet


def _terminate_group(
    argv: list[str], started: Callable[[], bool], settle_s: float = 0.0, sigint_ignored: bool = False
) -> tuple[int, list[str]]:
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if sigint_ignored else None
    p = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, preexec_fn=ignore)  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not started() and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(settle_s)
        assert p.poll() is None, p.communicate()[1][-3000:]
        os.killpg(p.pid, signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    return p.returncode, [line for line in err.splitlines() if line.strip() and " - WARNING - " not in line]


@pytest.fixture
def terminate_group():
    """``terminate_group(argv, started, settle_s=0, sigint_ignored=False)``: ``argv`` run from the repository in a
    session of its own, the whole group sent SIGTERM once ``started()`` holds (and ``settle_s`` more seconds), as a
    scheduler's stop or a session's end does; returns its exit status and its stderr lines other than the libraries'
    warnings. ``sigint_ignored``: started with SIGINT ignored, as a script's ``cmd &`` starts it. It fails if the
    command ended before the signal, and kills the group if it outlives 120 s after it."""
    return _terminate_group


def _repo_script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # a dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def repo_script():
    """``repo_script(name)``: ``scripts/<name>.py``, executed afresh as the module ``name``."""
    return _repo_script


@pytest.fixture
def slow_clock():
    """The emulator's robot model moves over an injectable clock. A test that reads the robot while it moves (a
    reply sent mid-step, a sample half a step away) runs it slower than the wall clock, so that a loaded CI box, which
    once read the robot only after it had arrived, still finds it under way; the motions stay well inside the
    client's timeouts and the server's heartbeat. After the test each slowed robot ends its motion and gets its own
    clock back (a module-scoped rig's next test starts on the real clock)."""
    slowed = []

    def slow(robot, factor: float = 3.0) -> None:
        own = robot.clock
        t0 = own()
        robot.clock = lambda: t0 + (own() - t0) / factor
        slowed.append((robot, own))

    yield slow
    for robot, own in reversed(slowed):
        robot.wait_done(timeout=2.0)
        robot.clock = own
