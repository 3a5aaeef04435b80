"""The GPU acceptance suite's runs: each check by name, the throughput the doctor reports, and running a check
in a fresh process.

Everything here runs the package's own code, in-process or in a fresh interpreter of this package. The trainers'
tiny GPU runs and the benchmark's GPU sweep are programs of the source checkout (``agents/``, ``benchmarks/``),
which an installed wheel does not have, so the package never starts them: ``benchmarks/gpu_acceptance.py``, in a
checkout, runs them and adds them to the same report (``doctor.gpu_report(programs=...)``). A GPU-side crash (a
PhysX or Vulkan abort) kills a process, not a Python exception: :func:`isolated` runs one check in a fresh
interpreter so that the doctor's report survives it as a FAIL.
"""

from __future__ import annotations

import importlib
import multiprocessing as mp
import os
import sys
import time
from typing import Any


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
)
"""the package's acceptance checks in report order: PhysX's GPU library (the others but WITHOUT_PHYSX_GPU need it),
the CPU sim's randomised frames (on a GPU machine rendered on CUDA), the env checks (acceptance.ENV_CHECKS); a
source checkout's ``benchmarks/gpu_acceptance.py`` adds the trainers' and the benchmark's runs after them"""


def run_named_check(name: str, sim_backend: str, num_envs: int) -> dict:
    """One check of :data:`CHECK_NAMES` as a :class:`CheckResult` dict (what :func:`isolated` can hand back)."""
    from maniskill_irb120.diagnostics.acceptance import ENV_CHECKS, timed_check

    if name == PHYSX_GPU:
        return timed_check(name, check_physx_gpu, sim_backend=sim_backend).to_dict()
    if name == RANDOMISED_FRAMES:
        from maniskill_irb120.diagnostics.acceptance import check_randomised_frames

        return timed_check(name, check_randomised_frames).to_dict()
    if name in ENV_CHECKS:
        return timed_check(name, ENV_CHECKS[name], sim_backend=sim_backend, num_envs=num_envs).to_dict()
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
