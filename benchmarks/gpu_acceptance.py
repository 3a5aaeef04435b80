"""The GPU acceptance report of a source checkout: ``maniskill-irb120 doctor --gpu``'s checks plus the runs that
only a checkout can make, the trainers' tiny ``--backend gpu`` runs and the benchmark's GPU sweep, in one report
(the JSON ``benchmarks/results/gpu_acceptance.json`` holds).

The trainers (``agents/``) and the benchmarks ship with the repository, not with the package, so the package's
doctor does not start them; this script does, as a user would (``python -m agents.ppo --backend gpu ...``), and
hands them to the doctor's report as its ``programs``. Each runs in its own process, so a GPU-side crash is its
FAIL and not the end of the report. The flags a run shares with a recipe come from ``maniskill_irb120/recipes.py``.

    python benchmarks/gpu_acceptance.py --jobs 8 --json-path benchmarks/results/gpu_acceptance.json
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from maniskill_irb120.recipes import RECIPES, STATE_PPO_NET

REPO = Path(__file__).resolve().parents[1]
TRAINERS = ("ppo", "sac", "dagger")
CAMERA_RECIPE = "dagger-rgbd-bf16"
"""the recipe the camera check runs (at toy sizes): the committed camera policies' recipe"""
CAMERA_DAGGER = "agents.dagger --obs rgbd"
CAMERA_DAGGER_ENVS = 8
"""the camera recipe's round (keypoint encoder, auxiliary head, --precision auto) at 8 envs: 84x84
frames of many more envs would time the renderer, not check the recipe"""
BENCHMARK = "sim_speed.py --gpu-only"
BENCH_ENVS = (16, 64)
"""num_envs of the benchmark's smoke sweep (small: it proves the script runs, the doctor times the rest)"""


def trainer_backend(sim_backend: str) -> str:
    return "gpu" if "cuda" in sim_backend or sim_backend == "gpu" else "cpu"


def trainer_command(name: str, sim_backend: str, num_envs: int, runs_dir: Path, obs: str | None = None) -> list[str]:
    """The smallest run of trainer ``name`` that still does its whole loop once: PPO two iterations, SAC its
    demos, cloning and a few online steps, DAgger its round 0 (one expert episode per env, a few updates)."""
    if name not in TRAINERS:
        raise ValueError(f"unknown trainer {name!r}; expected one of {TRAINERS}")
    common = ["--backend", trainer_backend(sim_backend), "--num-envs", str(num_envs), "--runs-dir", str(runs_dir)]
    common += ["--exp-name", name, "--no-progress", "--seed", "1"]
    if obs is not None:
        common += ["--obs", obs]
    if name == "ppo":
        steps = 8
        args = ["--num-steps", str(steps), "--total-timesteps", str(2 * steps * num_envs), "--num-minibatches", "2"]
        args += ["--eval-freq", "0", "--num-eval-episodes", "1", "--save-freq", "1", "--eval-episodes", "0"]
        if obs == "state":  # the RL-from-the-reward network (recipes.py): its normaliser on the GPU's tensors
            args += STATE_PPO_NET
    elif name == "sac":
        args = ["--budget-min", "0.05", "--demo-episodes", "1", "--bc-pretrain-updates", "5"]
        args += ["--critic-warmup-updates", "5", "--batch-size", "16", "--log-freq", "20", "--save-freq", "40"]
        args += ["--eval-episodes", "1", "--no-capture-video"]
    else:
        # the camera recipe (dagger-rgbd-bf16; --precision auto: bf16 on a CPU that has it) at toy sizes: its flags,
        # then this run's over them (round 0 as many updates as the other rounds)
        args = [*RECIPES[CAMERA_RECIPE].flags, "--initial-updates", "0"] if obs == "rgbd" else []
        args += ["--budget-min", "0.01", "--expert-episodes", str(num_envs), "--episodes-per-round", "1"]
        args += ["--updates-per-round", "5", "--batch-size", "16", "--eval-episodes", "1", "--no-capture-video"]
    return [sys.executable, "-m", f"agents.{name}", *common, *args]


def run_program(cmd: list[str], timeout_s: float, cwd: Path = REPO) -> tuple[int, dict | None, str]:
    """(exit status, the last stdout line as JSON if it is one, the output's last lines); run in the checkout,
    with it on PYTHONPATH, so that ``-m agents.X`` finds the trainers."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(cwd), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    try:
        out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return 124, None, f"timed out after {timeout_s:.0f} s"
    lines = out.stdout.strip().splitlines()
    result = None
    if lines:
        try:
            result = json.loads(lines[-1])
        except json.JSONDecodeError:
            result = None
    tail = "\n".join((out.stdout + "\n" + out.stderr).strip().splitlines()[-20:])
    return out.returncode, result if isinstance(result, dict) else None, tail


def last_line(tail: str) -> str:
    """The line of a failed program's output that says why (its last non-empty one, usually the exception)."""
    lines = [ln.strip() for ln in tail.splitlines() if ln.strip()]
    return lines[-1][:300] if lines else "no output"


def trainer_verdict(name: str, rc: int, result: dict | None, tail: str) -> tuple[bool, str]:
    """A trainer's tiny run passes when it exits 0 and its last line (the result JSON) shows the loop ran."""
    if rc != 0:
        return False, f"exit status {rc}: {last_line(tail)}"
    if result is None:
        return False, f"no result JSON on the last line: {last_line(tail)}"
    need = {"ppo": ("iterations", 2), "sac": ("env_steps", 1), "dagger": ("rounds", 1)}[name]
    got = result.get(need[0])
    if not isinstance(got, (int, float)) or got < need[1]:
        return False, f"{need[0]}={got!r}, expected >= {need[1]}"
    steps = "" if need[0] == "env_steps" else f", env_steps={result.get('env_steps')}"
    return True, f"{need[0]}={got}{steps}, {result.get('wall_clock_s', 0):.1f} s training"


def check_trainer(
    trainer: str, sim_backend: str, num_envs: int, obs: str | None = None, timeout_s: float = 600
) -> tuple[bool, str]:
    """``agents.TRAINER --backend gpu`` (or cpu) runs its tiny loop and writes its result."""
    with tempfile.TemporaryDirectory(prefix=f"accept_{trainer}_") as tmp:
        cmd = trainer_command(trainer, sim_backend, num_envs, Path(tmp), obs)
        return trainer_verdict(trainer, *run_program(cmd, timeout_s))


def check_camera_dagger(sim_backend: str, num_envs: int) -> tuple[bool, str]:
    """The camera recipe runs a round (at most :data:`CAMERA_DAGGER_ENVS` envs)."""
    return check_trainer("dagger", sim_backend, min(num_envs, CAMERA_DAGGER_ENVS), obs="rgbd")


def benchmark_command(json_path: Path, steps: int = 5) -> list[str]:
    cmd = [sys.executable, "benchmarks/sim_speed.py", "--gpu-only", "--gpu-num-envs", *map(str, BENCH_ENVS)]
    return cmd + ["--gpu-steps", str(steps), "--json", str(json_path)]


def benchmark_verdict(rc: int, report: dict | None, tail: str) -> tuple[bool, str]:
    if rc != 0:
        return False, f"exit status {rc}: {last_line(tail)}"
    rows = (report or {}).get("gpu_scaling") or []
    if [r.get("num_envs") for r in rows] != list(BENCH_ENVS):
        return False, f"the JSON's gpu_scaling has num_envs {[r.get('num_envs') for r in rows]}, expected {BENCH_ENVS}"
    if not all(r.get("env_steps_per_s", 0) > 0 for r in rows):
        return False, "a sweep row has no positive steps/s"
    rates = ", ".join(f"{r['num_envs']}: {r['env_steps_per_s']:.0f}" for r in rows)
    return True, f"sim_speed.py --gpu-only ran (rgbd steps/s {rates})"


def check_benchmark(sim_backend: str, num_envs: int = 0, timeout_s: float = 600) -> tuple[bool | None, str]:
    """``benchmarks/sim_speed.py --gpu-only`` runs its sweep end to end (tiny) and writes its JSON; its own
    ``BENCH_ENVS``, not ``num_envs``. SKIP off physx_cuda: the sweep is the GPU's."""
    if trainer_backend(sim_backend) != "gpu":
        return None, "the GPU sweep needs physx_cuda"
    with tempfile.TemporaryDirectory(prefix="accept_bench_") as tmp:
        path = Path(tmp) / "gpu.json"
        rc, _, tail = run_program(benchmark_command(path), timeout_s)
        report = json.loads(path.read_text()) if path.is_file() else None
        return benchmark_verdict(rc, report, tail)


PROGRAMS = {
    **{f"agents.{t}": functools.partial(check_trainer, t) for t in TRAINERS},
    CAMERA_DAGGER: check_camera_dagger,
    BENCHMARK: check_benchmark,
}
"""the checkout's checks in report order (after the package's): each called as ``fn(sim_backend=..., num_envs=...)``
with the report's trainer batch size"""


def git_commit(root: Path = REPO) -> str | None:
    """The checkout's commit (short), so that a report names the code that ran; None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        )
        return (out.stdout.strip() or None) if out.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


@dataclass
class Args:
    json: bool = False
    """print the report as JSON (default: plain text)"""
    json_path: Optional[Path] = None
    """also write the report there (benchmarks/results/gpu_acceptance.json is the committed one)"""
    jobs: int = 1
    """checks side by side, each in its own process (the obs-mode sweep split per task and mode)"""
    trainer_envs: int = 64
    """num_envs of the trainers' tiny runs (the camera recipe's at most 8)"""


def main(args: Args) -> int:
    """0 when every check passes, 1 when one fails, 2 without a CUDA device (as ``doctor --gpu``)."""
    from maniskill_irb120.diagnostics.doctor import gpu_main

    if args.jobs < 1:
        raise SystemExit(f"--jobs {args.jobs}: expected 1 or more")
    if args.trainer_envs < 1:
        raise SystemExit(f"--trainer-envs {args.trainer_envs}: expected 1 or more")
    return gpu_main(
        json_output=args.json,
        json_path=None if args.json_path is None else str(args.json_path),
        jobs=args.jobs,
        programs=PROGRAMS,
        trainer_envs=args.trainer_envs,
        commit=git_commit(),
    )


if __name__ == "__main__":
    import tyro

    sys.exit(main(tyro.cli(Args)))
