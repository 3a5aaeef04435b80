"""Bad input to a benchmark is one line and exit status 2, never a traceback: each benchmark CLI is run as a user runs
it (``python -m benchmarks.NAME``) with one bad flag, and must say so in one stderr line naming itself and the flag.
Each case is refused by the benchmark's ``check`` (or tyro's parse) before any env, run or emulator starts, so a case
costs the interpreter's start and the module's imports; the cases run side by side to keep the file short."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "benchmarks"

# module -> (one bad flag and what else the case needs, the flag its one line must name); {tmp} is the test's folder
# (algorithms' --conf-file, a probe's config, must exist, and a probe needs its own --out-dir and --runs-dir)
CASES = {
    "adapter_latency": (["--steps", "0"], "--steps"),
    "algorithms": (
        ["--conf-file", "{tmp}/no-such.yml", "--out-dir", "{tmp}/out", "--runs-dir", "{tmp}/runs"],
        "--conf-file",
    ),
    "camera_ppo_split": (["--env-steps", "0"], "--env-steps"),
    "gpu_acceptance": (["--jobs", "0"], "--jobs"),
    "headline": (["--wrtie"], "--wrtie"),
    "learner_speed": (["--rounds", "0"], "--rounds"),
    "learning": (["--recipes", "no-such-recipe"], "--recipes"),
    "original_experiment": (["--recipes", "no-such-recipe"], "--recipes"),
    "pybullet_original": (["--modes", "no-such-mode"], "--modes"),
    "rllib_speed": (["--batch", "0"], "--batch"),
    "sim2real_gap": (["--workers", "0"], "--workers"),
    "sim_speed": (["--rounds", "0"], "--rounds"),
    "sysid_recovery": (["--repeats", "0"], "--repeats"),
}


def run(module: str, tmp: Path) -> subprocess.CompletedProcess:
    argv = [a.replace("{tmp}", str(tmp)) for a in CASES[module][0]]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", f"benchmarks.{module}", *argv]
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=180)


def own_lines(stderr: str) -> list[str]:
    """stderr less the lines libraries print on their own: ManiSkill's log warnings, PyBullet's banner at import."""
    return [
        line
        for line in stderr.splitlines()
        if line.strip() and " - WARNING - " not in line and not line.startswith("pybullet build time:")
    ]


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, subprocess.CompletedProcess]:
    """Every case's finished process, run side by side (each is mostly its imports)."""
    tmp = tmp_path_factory.mktemp("cli_errors")
    with ThreadPoolExecutor(max_workers=max(2, min(len(CASES), os.cpu_count() or 2))) as pool:
        done = dict(zip(CASES, pool.map(run, CASES, [tmp] * len(CASES))))
    assert not (tmp / "out").exists() and not (tmp / "runs").exists()  # refused before anything was written
    return done


def test_every_benchmark_cli_has_a_case():
    assert set(CASES) == {p.stem for p in BENCH.glob("*.py") if p.stem != "__init__"}


@pytest.mark.parametrize("module", list(CASES))
def test_bad_flag_is_one_line_and_exit_2(results, module):
    flag = CASES[module][1]
    out = results[module]
    lines = own_lines(out.stderr)
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert out.returncode == 2, (out.returncode, out.stderr[-3000:])
    assert len(lines) == 1, out.stderr[-3000:]
    assert lines[0].startswith(f"benchmarks.{module}: error: ") and flag in lines[0], lines[0]
    assert out.stdout == "", out.stdout[-3000:]


def test_only_check_errors_are_one_line_a_run_keeps_its_traceback(capsys):
    """``entry`` in process: a check's ValueError is one line and status 2 before ``main`` starts, a ValueError
    ``main`` raises propagates as it was (a failed run, whose traceback says where), a Ctrl-C is one line and 130."""
    from dataclasses import dataclass

    from benchmarks.lib.cli import entry

    @dataclass
    class Args:
        steps: int = 1

    def check(args: Args) -> None:
        if args.steps < 1:
            raise ValueError(f"--steps {args.steps}: expected 1 or more")

    ran = []
    with pytest.raises(SystemExit) as stop:
        entry("benchmarks.x", Args, ran.append, check, argv=["--steps", "0"])
    assert stop.value.code == 2 and ran == []
    assert capsys.readouterr().err == "benchmarks.x: error: --steps 0: expected 1 or more\n"

    def fails(args: Args) -> None:
        raise ValueError("a failed run")

    with pytest.raises(ValueError, match="a failed run"):
        entry("benchmarks.x", Args, fails, check, argv=[])

    def interrupted(args: Args) -> None:
        raise KeyboardInterrupt

    with pytest.raises(SystemExit) as stop:
        entry("benchmarks.x", Args, interrupted, check, argv=[])
    assert stop.value.code == 130 and capsys.readouterr().err == "benchmarks.x: interrupted\n"
    assert entry("benchmarks.x", Args, lambda a: a.steps * 2, check, argv=["--steps", "3"]) == 6
    with pytest.raises(SystemExit) as stop:
        entry("benchmarks.x", Args, lambda a: 1, check, argv=[], exit_status=True)
    assert stop.value.code == 1
