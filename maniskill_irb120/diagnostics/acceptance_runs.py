"""The GPU acceptance runs that are whole programs: the trainers' tiny runs, the benchmark's GPU sweep, the
throughput the doctor reports, and running a check in a fresh process.

The trainers (``agents/``) and the benchmark (``benchmarks/``) live in the source checkout, not in the package:
the library never imports them, it runs them as a user would (``python -m agents.ppo --backend gpu ...``), so
a check here needs a checkout and says SKIP without one. The flags a check shares with a recipe come from
``maniskill_irb120/recipes.py``, the recipes' one home. A GPU-side crash (a PhysX or Vulkan abort) kills a
process, not a Python exception: :func:`isolated` runs one check in a fresh interpreter so that the doctor's
report survives it as a FAIL.
"""

from __future__ import annotations

import importlib
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from maniskill_irb120.recipes import RECIPES, STATE_PPO_NET

TRAINERS = ("ppo", "sac", "dagger")
CHECKOUT_HINT = "clone the repository and pip install -e . there"
CAMERA_RECIPE = "dagger-rgbd-bf16"
"""the recipe the camera check runs (at toy sizes): the committed camera policies' recipe"""
BENCH_ENVS = (16, 64)
"""num_envs of the benchmark's smoke sweep (small: it proves the script runs, the doctor times the rest)"""


def source_checkout() -> Path | None:
    """The repository this package runs from (an editable install or PYTHONPATH), if it has the trainers."""
    root = Path(__file__).resolve().parents[2]
    return root if (root / "agents" / "ppo.py").is_file() and (root / "benchmarks" / "sim_speed.py").is_file() else None


def trainer_backend(sim_backend: str) -> str:
    return "gpu" if "cuda" in sim_backend or sim_backend == "gpu" else "cpu"


def trainer_command(name: str, sim_backend: str, num_envs: int, runs_dir: Path, obs: str | None = None) -> list[str]:
    """The smallest run of trainer ``name`` that still does its whole loop once: PPO two iterations, SAC its
    demos, cloning and a few online steps, DAgger its round 0 (one expert episode per env, a few updates)."""
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
    elif name == "dagger":
        # the camera recipe (dagger-rgbd-bf16; --precision auto: bf16 on a CPU that has it) at toy sizes: its flags,
        # then this run's over them (round 0 as many updates as the other rounds)
        args = [*RECIPES[CAMERA_RECIPE].flags, "--initial-updates", "0"] if obs == "rgbd" else []
        args += ["--budget-min", "0.01", "--expert-episodes", str(num_envs), "--episodes-per-round", "1"]
        args += ["--updates-per-round", "5", "--batch-size", "16", "--eval-episodes", "1", "--no-capture-video"]
    else:
        raise ValueError(f"unknown trainer {name!r}; expected one of {TRAINERS}")
    return [sys.executable, "-m", f"agents.{name}", *common, *args]


def run_program(cmd: list[str], cwd: Path, timeout_s: float) -> tuple[int, dict | None, str]:
    """(exit status, the last stdout line as JSON if it is one, the output's last lines)."""
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
) -> tuple[bool | None, str]:
    """``agents.TRAINER --backend gpu`` (or cpu) runs its tiny loop and writes its result."""
    root = source_checkout()
    if root is None:
        return None, f"needs a source checkout: agents/ ships with the repository, not the package ({CHECKOUT_HINT})"
    with tempfile.TemporaryDirectory(prefix=f"accept_{trainer}_") as tmp:
        cmd = trainer_command(trainer, sim_backend, num_envs, Path(tmp), obs)
        return trainer_verdict(trainer, *run_program(cmd, root, timeout_s))


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


def check_benchmark(timeout_s: float = 600) -> tuple[bool | None, str]:
    """``benchmarks/sim_speed.py --gpu-only`` runs its sweep end to end (tiny) and writes its JSON."""
    root = source_checkout()
    if root is None:
        return (
            None,
            f"needs a source checkout: benchmarks/ ships with the repository, not the package ({CHECKOUT_HINT})",
        )
    with tempfile.TemporaryDirectory(prefix="accept_bench_") as tmp:
        path = Path(tmp) / "gpu.json"
        rc, _, tail = run_program(benchmark_command(path), root, timeout_s)
        report = json.loads(path.read_text()) if path.is_file() else None
        return benchmark_verdict(rc, report, tail)


# --------------------------------------------------------------------------- throughput
def measure_batched(
    env_id: str, num_envs: int, steps: int, seed: int, backend: str = "gpu", obs_mode: str = "rgbd"
) -> dict:
    """Batched env steps/s as training sees them: ``make_vec_env`` (ManiSkillVectorEnv, auto-reset of
    finished envs), a fresh seeded uniform action every step. The GPU sweep (the doctor's and
    ``benchmarks/sim_speed.py``'s); ``backend="inprocess"`` runs the same loop on one CPU env (how the tests
    check it)."""
    import torch

    from maniskill_irb120 import make_vec_env

    extra = dict(render_backend="none") if obs_mode in ("state", "state_dict", "none") else {}
    envs = make_vec_env(env_id, num_envs, backend=backend, obs_mode=obs_mode, record_metrics=True, **extra)
    dev = envs.device
    gen = torch.Generator(device=dev).manual_seed(seed)
    shape = (num_envs, *envs.single_action_space.shape)
    action = lambda: torch.rand(shape, generator=gen, device=dev) * 2 - 1  # noqa: E731
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    envs.reset(seed=seed)
    free0, total = torch.cuda.mem_get_info() if dev.type == "cuda" else (0, 0)
    for _ in range(5):
        envs.step(action())
    sync()
    episodes = 0
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = envs.step(action())
        episodes += int((term | trunc).sum())
    sync()
    dt = time.perf_counter() - t0
    free1 = torch.cuda.mem_get_info()[0] if dev.type == "cuda" else 0
    envs.close()
    return dict(
        num_envs=num_envs,
        backend=backend,
        obs_mode=obs_mode,
        env_steps_per_s=steps * num_envs / dt,
        episodes_finished=episodes,
        gpu_mem_used_gb=(total - min(free0, free1)) / 2**30,
    )


# --------------------------------------------------------------------------- isolation
def _child(conn, module: str, fn: str, kwargs: dict) -> None:
    # what a check prints (SAPIEN's download notice, warnings) goes to stderr: stdout is the report's
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    try:
        conn.send(("ok", getattr(importlib.import_module(module), fn)(**kwargs)))
    except BaseException as e:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(e).__name__}: {str(e).strip()[:300]}"))


def isolated(module: str, fn: str, /, timeout_s: float = 600, **kwargs) -> Any:
    """``module.fn(**kwargs)`` in a fresh interpreter (spawn); its return value, or RuntimeError saying how the
    process ended (an exception's message, a crash's exit status, or the timeout)."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, module, fn, kwargs))
    proc.start()
    child.close()
    try:
        if not parent.poll(timeout_s):
            proc.kill()
            raise RuntimeError(f"{fn} timed out after {timeout_s:.0f} s")
        status, value = parent.recv()
    except EOFError:
        proc.join()
        raise RuntimeError(f"{fn} crashed (exit status {proc.exitcode}) before it returned") from None
    finally:
        parent.close()
    proc.join()
    if status != "ok":
        raise RuntimeError(value)
    return value


# --------------------------------------------------------------------------- PhysX's GPU library
def check_physx_gpu(sim_backend: str) -> tuple[bool | None, str]:
    """SAPIEN turns PhysX's GPU backend on: every ``physx_cuda`` check needs it, and SAPIEN fetches its library
    from GitHub on first use, which an offline GPU machine cannot (each check would then fail alike)."""
    if "cuda" not in sim_backend:
        return None, f"{sim_backend} needs no GPU library"
    import sapien

    from maniskill_irb120.maniskill_compat import physx_gpu_library

    path, url = physx_gpu_library()
    had = path.is_file()
    try:
        sapien.physx.enable_gpu()
    except Exception as e:  # noqa: BLE001 - the reason is the verdict
        why = f"{type(e).__name__}: {str(e).strip().splitlines()[0][:160] if str(e).strip() else ''}"
        where = "is there but did not load" if had else "is missing and fetching it failed"
        return False, f"{path} {where} ({why}); without internet access unzip {url} into {path.parent}"
    return True, f"PhysX {sapien.physx.version()} GPU library loaded ({path}{'' if had else ', fetched now'})"


# --------------------------------------------------------------------------- the report's checks
CAMERA_DAGGER = "agents.dagger --obs rgbd"
CAMERA_DAGGER_ENVS = 8
"""the camera recipe's round (keypoint encoder, auxiliary head, --precision auto) at 8 envs: 84x84
frames of many more envs would time the renderer, not check the recipe"""
PHYSX_GPU = "physx gpu library"
RANDOMISED_FRAMES = "randomised frames, cpu physics"
WITHOUT_PHYSX_GPU = (RANDOMISED_FRAMES,)
"""the checks that still run when PhysX's GPU library is missing (they do not turn physx_cuda on)"""
CHECK_NAMES = (
    PHYSX_GPU,
    RANDOMISED_FRAMES,
    "obs modes",
    "partial resets",
    "controller targets",
    "contacts",
    "rgbd frames",
    "appearance per env",
    "agents.ppo",
    "agents.sac",
    "agents.dagger",
    CAMERA_DAGGER,
    "sim_speed.py --gpu-only",
)
"""the acceptance suite in report order: PhysX's GPU library (the others but WITHOUT_PHYSX_GPU need it), the CPU
sim's randomised frames (on a GPU machine rendered on CUDA), the env checks (acceptance.ENV_CHECKS), the trainers,
the benchmark"""


def run_named_check(name: str, sim_backend: str, num_envs: int, trainer_envs: int = 64) -> dict:
    """One check of :data:`CHECK_NAMES` as a :class:`CheckResult` dict (what :func:`isolated` can hand back)."""
    from maniskill_irb120.diagnostics.acceptance import ENV_CHECKS, CheckResult, timed_check

    if name == PHYSX_GPU:
        return timed_check(name, check_physx_gpu, sim_backend=sim_backend).to_dict()
    if name == RANDOMISED_FRAMES:
        from maniskill_irb120.diagnostics.acceptance import check_randomised_frames

        return timed_check(name, check_randomised_frames).to_dict()
    if name in ENV_CHECKS:
        return timed_check(name, ENV_CHECKS[name], sim_backend=sim_backend, num_envs=num_envs).to_dict()
    if name == CAMERA_DAGGER:
        n = min(trainer_envs, CAMERA_DAGGER_ENVS)
        return timed_check(
            name, check_trainer, trainer="dagger", sim_backend=sim_backend, num_envs=n, obs="rgbd"
        ).to_dict()
    if name.startswith("agents."):
        trainer = name.split(".", 1)[1]
        return timed_check(
            name, check_trainer, trainer=trainer, sim_backend=sim_backend, num_envs=trainer_envs
        ).to_dict()
    if name == "sim_speed.py --gpu-only":
        if trainer_backend(sim_backend) != "gpu":
            return CheckResult(name, None, "the GPU sweep needs physx_cuda").to_dict()
        return timed_check(name, check_benchmark).to_dict()
    raise ValueError(f"unknown check {name!r}; expected one of {CHECK_NAMES}")


def run_obs_mode_check(env_id: str, obs_mode: str, sim_backend: str, num_envs: int) -> dict:
    """One task in one obs mode: a part of the ``obs modes`` check that :func:`doctor.gpu_report` runs in its own
    process when it runs checks side by side (the whole sweep, 24 scenes one after another, is its longest)."""
    from maniskill_irb120.diagnostics.acceptance import check_obs_modes, timed_check

    name = f"obs modes [{env_id} {obs_mode}]"
    kw = dict(sim_backend=sim_backend, num_envs=num_envs, env_ids=[env_id], obs_modes=[obs_mode])
    return timed_check(name, check_obs_modes, **kw).to_dict()


def merge_parts(name: str, parts: list[dict], seconds: float) -> dict:
    """One check's result from its parts: FAIL if a part failed (naming each), SKIP only if every part skipped;
    ``seconds`` is the wall-clock time from the first part's start to the last part's end."""
    failed = [p for p in parts if p["ok"] is False]
    if failed:
        ok, reason = (
            False,
            f"{len(failed)} of {len(parts)} parts failed: " + "; ".join(f"{p['name']}: {p['reason']}" for p in failed),
        )
    elif all(p["ok"] is None for p in parts):
        ok, reason = None, parts[0]["reason"] if parts else "no parts"
    else:
        ok, reason = True, f"all {len(parts)} parts passed, each in its own process; the first: {parts[0]['reason']}"
    return dict(
        name=name,
        ok=ok,
        status="SKIP" if ok is None else ("PASS" if ok else "FAIL"),
        reason=reason,
        seconds=round(seconds, 2),
    )
