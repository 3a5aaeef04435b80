"""Errors inside the CPU vector env's worker processes reach a script as one line, as a user's script meets them.

A script (written here, run as a program) steps ``make_vec_env(..., backend="cpu")`` under ``usage_errors``: a NaN
action and a batch of the wrong shape are refused before anything steps, in one line each, and the envs step on
afterwards; then an env that raises inside its worker ends the script with one line naming the env and the error,
exit status 2, and none of the worker's traceback. Ctrl-C (SIGINT to the whole process group, as a terminal sends
it) while the workers step leaves the script's own line and status 130: the workers ignore it, the parent closes
them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

WRAPPER = '''
import multiprocessing

import gymnasium as gym


class FailsInWorker(gym.Wrapper):
    """Raises on its third step, in a worker process only (env 0 steps in the script's own process)."""

    def __init__(self, env):
        super().__init__(env)
        self.steps = 0

    def step(self, action):
        self.steps += 1
        if self.steps == 3 and multiprocessing.parent_process() is not None:
            raise RuntimeError("the gripper joint is gone")
        return self.env.step(action)
'''

SCRIPT = """
import sys

import torch

from maniskill_irb120 import make_vec_env
from maniskill_irb120.errors import usage_errors
from failing import FailsInWorker

if __name__ == "__main__":
    wrappers = [FailsInWorker] if sys.argv[1] == "fail" else []
    with usage_errors("script.py"):
        env = make_vec_env("GraspLift-IRB120-v1", 2, backend="cpu", wrappers=wrappers, obs_mode="state",
                           render_backend="none")
        env.reset(seed=0)
        try:
            for bad in (torch.full((2, 5), float("nan")), torch.zeros(3, 5)):
                try:
                    env.step(bad)
                except ValueError as e:
                    print("refused:", e, flush=True)
            env.step(torch.zeros(2, 5))
            print("stepped after the refusals", flush=True)
            for t in range(10_000):
                env.step(torch.zeros(2, 5))
                if t == 5:
                    print("stepping", flush=True)
        except KeyboardInterrupt:
            env.close()
            print("interrupted; the envs are closed", file=sys.stderr, flush=True)
            raise SystemExit(130)
        finally:
            env.close()
"""


def start(tmp_path: Path, mode: str) -> subprocess.Popen:
    (tmp_path / "failing.py").write_text(textwrap.dedent(WRAPPER))
    (tmp_path / "script.py").write_text(textwrap.dedent(SCRIPT))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)]))
    return subprocess.Popen(
        [sys.executable, "script.py", mode],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, which the Ctrl-C below goes to, as a terminal's does
        # SIGINT's default, as at a terminal, even where pytest was started as a background job (``cmd &`` in a
        # script) and so inherited SIGINT ignored: Python then keeps it ignored and the Ctrl-C below would be lost
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def own_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip() and " - WARNING - " not in line]


def test_bad_actions_are_refused_and_a_failing_worker_env_is_one_line(tmp_path):
    p = start(tmp_path, "fail")
    out, err = p.communicate(timeout=300)
    lines = out.splitlines()
    assert lines[0].startswith("refused: actions contain NaN or inf for env index [0, 1]"), out
    assert lines[1] == "refused: actions have shape (3, 5), expected (2, 5) (one action per env); nothing was stepped"
    assert lines[2] == "stepped after the refusals", out
    assert p.returncode == 2, err[-3000:]
    assert own_lines(err) == [
        "script.py: env 1 raised RuntimeError in its worker process: the gripper joint is gone; that worker is shut "
        "down, so close() this vector env and make a new one with make_vec_env(...) (the worker's traceback: the "
        "exception's worker_traceback)"
    ], err[-3000:]


def test_ctrl_c_leaves_no_worker_traceback(tmp_path):
    p = start(tmp_path, "run")
    try:
        for line in p.stdout:  # the workers are stepping
            if line.strip() == "stepping":
                break
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err[-3000:]
    assert own_lines(err) == ["interrupted; the envs are closed"], err[-3000:]
