"""Bad input answered in one line: every command line a newcomer meets first (``maniskill-irb120``'s subcommands,
``examples/*.py``) is run here as a program, as a user runs it, with a wrong env id, a missing or unreadable file,
a count below 1, a misspelt flag or a malformed value, and must exit with status 2 and one stderr line that names
the problem and the fix, with no traceback. Each is refused before an env is built, so a case takes the
interpreter's start and imports only: one case ("wrong env id") runs in a fresh interpreter, and the others in
a child forked from one interpreter that has imported the libraries every case imports (torch, gymnasium,
ManiSkill, SAPIEN, tyro, Stable-Baselines3, skrl; ~7 s a case otherwise). The child runs the command line as
``python`` does (``runpy``, ``__main__``, ``sys.argv``, the exit status from ``SystemExit``, an uncaught
exception's traceback on stderr); this package's and the script's own modules are imported afresh in it.

And a script that follows the ``num_envs > 1`` error's advice (``make_vec_env(..., backend="cpu")``) without an
``if __name__ == "__main__":`` guard is told so in one line by the worker that imported it again, instead of
Python's two chained multiprocessing tracebacks."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TASKS = "GraspLift-IRB120-v1, StackCube-IRB120-v1, TableClearing-IRB120-v1"


def run(args: list[str], cwd: Path = REPO, timeout: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


PRELOADED = r"""
import json, os, runpy, signal, sys, tempfile, traceback

import torch, gymnasium, sapien, mani_skill.envs, tyro  # noqa: F401  (what every case imports)

for name in ("stable_baselines3", "skrl.agents.torch.ppo", "skrl.trainers.torch"):
    try:
        __import__(name)
    except ImportError:
        pass
base = set(sys.modules)
ours = ("maniskill_irb120", "agents", "examples", "scripts")
assert not [m for m in base if m.split(".")[0] in ours], "the cases' own modules must be imported afresh"
for line in sys.stdin:
    case = json.loads(line)
    err = tempfile.TemporaryFile()
    pid = os.fork()
    if pid == 0:
        signal.alarm(180)  # a case that hangs (a lock held across the fork, say) ends as a failure, not a stuck suite
        os.chdir(case["cwd"])
        out = os.open(os.devnull, os.O_WRONLY)
        os.dup2(out, 1)
        os.dup2(err.fileno(), 2)
        args, code = case["args"], 0
        try:
            if args[0] == "-m":
                sys.argv = [args[1], *args[2:]]
                sys.path.insert(0, case["cwd"])
                runpy.run_module(args[1], run_name="__main__", alter_sys=True)
            else:
                sys.argv = list(args)
                sys.path.insert(0, os.path.dirname(os.path.abspath(args[0])))
                runpy.run_path(args[0], run_name="__main__")
        except SystemExit as e:
            if e.code is None or isinstance(e.code, int):
                code = e.code or 0
            else:
                print(e.code, file=sys.stderr)
                code = 1
        except BaseException:
            traceback.print_exc()
            code = 1
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    err.seek(0)
    answer = dict(returncode=os.waitstatus_to_exitcode(status), stderr=err.read().decode(errors="replace"))
    print(json.dumps(answer), flush=True)
"""


@pytest.fixture(scope="module")
def preloaded():
    """``run(args)`` as :func:`run` does, in a child forked from an interpreter with the libraries imported."""
    import json

    env = dict(os.environ, PYTHONPATH=str(REPO))
    server = subprocess.Popen(
        [sys.executable, "-c", PRELOADED], cwd=REPO, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )

    def run_forked(args: list[str]) -> subprocess.CompletedProcess:
        server.stdin.write(json.dumps(dict(args=args, cwd=str(REPO))) + "\n")
        server.stdin.flush()
        line = server.stdout.readline()
        assert line, f"the preloaded interpreter ended (status {server.poll()})"
        answer = json.loads(line)
        return subprocess.CompletedProcess(args, answer["returncode"], "", answer["stderr"])

    yield run_forked
    server.stdin.close()
    server.wait(timeout=60)


def own_lines(stderr: str) -> list[str]:
    """stderr less the log lines libraries print on their own (ManiSkill's render-device warning)."""
    return [line for line in stderr.splitlines() if line.strip() and " - WARNING - " not in line]


def cli(*args: str) -> list[str]:
    return ["-m", "maniskill_irb120.cli", *args]


CASES = {
    "wrong env id": (
        cli("expert", "--env-id", "GraspLift-v1"),
        ["unknown env id 'GraspLift-v1'", "did you mean 'GraspLift-IRB120-v1'", TASKS],
    ),
    "wrong env id, sim2real-eval": (
        cli("sim2real-eval", "--env-id", "stackcube-irb120-v1"),
        ["did you mean 'StackCube-IRB120-v1'", TASKS],
    ),
    "missing policy": (
        cli("sim2real-eval", "--policy", "{tmp}/missing.pt", "--out", "{tmp}/out"),
        ["--policy", "missing.pt", "neither 'expert' nor an existing checkpoint file"],
    ),
    "not a checkpoint": (
        cli("sim2real-eval", "--policy", "{tmp}/notes.txt", "--out", "{tmp}/out"),
        ["notes.txt is not a readable torch checkpoint", "export-policy"],
    ),
    "sysid, missing log": (cli("sysid", "--log", "{tmp}/nowhere"), ["--log", "nowhere: no such folder", "--out"]),
    "expert, negative episodes": (cli("expert", "--episodes", "-1"), ["--episodes -1: give a whole number >= 1"]),
    "collect-demos, zero episodes": (cli("collect-demos", "--episodes", "0"), ["--episodes 0"]),
    "example, wrong env id": (["examples/sb3_ppo.py", "--env-id", "GraspLift"], ["sb3_ppo.py: unknown env id"]),
    "demo, zero episodes": (["examples/demo.py", "--episodes", "0"], ["demo.py: --episodes 0"]),
    "collision frames, misspelt shift": (
        ["scripts/collision_frames.py", "--shift", "camera_fovv=75"],
        ["collision_frames.py: --shift 'camera_fovv=75'", "camera_fov"],
    ),
    "collision frames, negative seed": (
        ["scripts/collision_frames.py", "--seed", "-5"],
        ["collision_frames.py: --seed -5: episode seeds are 0 or more"],
    ),
    "collision frames, missing policy": (
        ["scripts/collision_frames.py", "--policy", "{tmp}/missing.pt"],
        ["collision_frames.py: --policy", "missing.pt"],
    ),
    "appearance failures, missing report": (
        ["scripts/appearance_failures.py", "--reports", "{tmp}/missing/report.json"],
        ["scripts.appearance_failures: error: --reports", "missing/report.json: no such file"],
    ),
    "appearance failures, not a report": (
        ["scripts/appearance_failures.py", "--reports", "{tmp}/notes.txt"],
        ["--reports", "notes.txt: not JSON"],
    ),
    "gripper chatter, misspelt env id": (
        ["scripts/gripper_chatter.py", "--env-id", "GraspLift-v1"],
        ["scripts.gripper_chatter: error: unknown env id 'GraspLift-v1'", "did you mean 'GraspLift-IRB120-v1'"],
    ),
    "gripper chatter, another task's policy": (
        ["scripts/gripper_chatter.py", "--env-id", "GraspLift-IRB120-v1", "--policy", "ppo-state-tableclearing-sel-s1"],
        ["--policy ppo-state-tableclearing-sel-s1: trained on TableClearing-IRB120-v1, not --env-id GraspLift"],
    ),
    "example, zero envs": (["examples/sb3_ppo.py", "--num-envs", "0"], ["sb3_ppo.py: --num-envs 0: give a whole"]),
    "example, zero steps": (["examples/skrl_ppo.py", "--total-timesteps", "0"], ["--total-timesteps 0: give a whole"]),
    "example, negative held-out episodes": (["examples/sb3_sac.py", "--eval-episodes", "-1"], ["--eval-episodes -1"]),
    "misspelt flag": (
        cli("expert", "--episode", "3"),
        ["Unrecognized options: --episode, 3", "did you mean --episodes?", "maniskill-irb120 expert --help"],
    ),
    "malformed value, example": (["examples/demo.py", "--episodes", "abc"], ["demo.py: Error parsing --episodes"]),
    "trainer, misspelt recipe": (
        ["-m", "agents.ppo", "--recipe", "ppo-stat"],
        ["--recipe 'ppo-stat': no such recipe (did you mean 'ppo-state'?)", "agents.ppo's recipes"],
    ),
    "trainer, wrong env id": (
        ["-m", "agents.dagger", "--env-id", "Foo-v1", "--total-env-steps", "100"],
        ["agents.dagger: unknown env id 'Foo-v1'", TASKS],
    ),
    "trainer, zero budget": (["-m", "agents.sac", "--total-env-steps", "0"], ["--total-env-steps must be a positive"]),
}
NEEDS = {"example, wrong env id": "stable_baselines3"}
FRESH = "wrong env id"
"""the case run in a fresh interpreter, as a user runs it (imports and all): the others share the preloaded one"""


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_and_exit_status_2(case, tmp_path, preloaded):
    if case in NEEDS:
        pytest.importorskip(NEEDS[case])
    (tmp_path / "notes.txt").write_text("not a checkpoint\n")
    args, names = CASES[case]
    r = (run if case == FRESH else preloaded)([a.replace("{tmp}", str(tmp_path)) for a in args])
    lines = own_lines(r.stderr)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    assert len(lines) == 1, lines
    for name in names:
        assert name in lines[0], (name, lines[0])


def test_a_script_without_the_main_guard_is_told_so_in_one_line(tmp_path):
    """The workers of ``backend="cpu"`` import the script again (forkserver); without the guard each would build
    envs of its own. The worker says so in one line and stops; the parent reports a worker that exited while
    starting, not a lost pipe."""
    script = tmp_path / "noguard.py"
    script.write_text(
        textwrap.dedent(
            """
            from maniskill_irb120 import make_vec_env

            env = make_vec_env("GraspLift-IRB120-v1", 2, backend="cpu")
            env.close()
            """
        )
    )
    r = run([str(script)], cwd=tmp_path)
    assert r.returncode != 0
    lines = own_lines(r.stderr)
    told = [line for line in lines if line.startswith("make_vec_env(backend='cpu') was called while a worker")]
    assert len(told) == 1 and 'if __name__ == "__main__":' in told[0], r.stderr[-3000:]
    assert "bootstrapping phase" not in r.stderr and "Connection reset by peer" not in r.stderr, r.stderr[-3000:]
    assert r.stderr.count("Traceback") == 1 and len(lines) < 15, r.stderr[-3000:]
    assert lines[-1].startswith("RuntimeError: a CPU env worker process exited while starting")


@pytest.mark.parametrize(
    "given, meant",
    [
        ("grasplift-irb120-v1", "GraspLift-IRB120-v1"),  # case
        ("TableClearing-v1", "TableClearing-IRB120-v1"),
        ("PickCube-v2", "PickCube-v1"),  # ManiSkill's own, when near-exact
        ("PushCube", "PushCube-v1"),
        ("Foo-v1", None),  # no id is near: none named (not Acrobot-v1 for sharing "-v1")
    ],
)
def test_the_nearest_env_id_is_named_only_when_near(given, meant):
    import maniskill_irb120  # noqa: F401  (registers the tasks)
    from maniskill_irb120.envs import check_env_id, task_ids
    from maniskill_irb120.errors import UsageError

    assert task_ids() == TASKS.split(", ")
    with pytest.raises(UsageError) as e:
        check_env_id(given)
    assert (f"(did you mean {meant!r}?)" in str(e.value)) if meant else "did you mean" not in str(e.value)
