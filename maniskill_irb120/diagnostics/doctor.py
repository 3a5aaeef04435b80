"""``maniskill-irb120 doctor``: what a user runs when rendering fails.

It does not trust the driver list alone: it renders one 84x84 RGB-D frame with SAPIEN, which is
exactly what the env's hand camera needs, and reports the device that did it.
"""

from __future__ import annotations

import importlib.metadata as md
import platform
import re
import time
from collections.abc import Callable, Mapping

FIX_HINT = (
    "No usable Vulkan device. On Debian 12 (root): add the bookworm-backports suite and run "
    "'apt-get install -t bookworm-backports mesa-vulkan-drivers libvulkan1' (Mesa >= 24.3; "
    "Debian 12's own Mesa 22.3 lacks VK_KHR_external_semaphore_fd, which SAPIEN needs). "
    "On other systems install a Vulkan driver (NVIDIA driver, or Mesa lavapipe >= 24.3) and the "
    "Vulkan loader (libvulkan1). Or run state-only with render_backend='none'."
)


def _devices(summary: str) -> list[dict]:
    devices = []
    for block in re.split(r"\n(?=\S)", summary.strip()):
        head = re.match(r"(\w+):\s*(.*)", block)
        if not head:
            continue
        fields = dict(re.findall(r"^\s+(\w+):?\s+(-?\w+)", block, flags=re.M))
        name = head.group(2)
        devices.append(
            dict(
                kind=head.group(1),
                name=name,
                supported=fields.get("Supported") == "1",
                cpu=any(s in name.lower() for s in ("llvmpipe", "lavapipe", "swiftshader")),
                cuda_id=int(fields.get("cudaId", -1)),
            )
        )
    return devices


def _render_probe() -> dict:
    """Render one 84x84 RGB-D frame of a box; returns timing and whether depth makes sense."""
    import numpy as np
    import sapien

    # explicit systems: a bare sapien.Scene() fails once ManiSkill has set up its own render device
    scene = sapien.Scene([sapien.physx.PhysxCpuSystem(), sapien.render.RenderSystem()])
    scene.set_ambient_light([0.5, 0.5, 0.5])
    builder = scene.create_actor_builder()
    builder.add_box_visual(half_size=[0.1, 0.1, 0.1], material=[1, 0, 0])
    builder.build_static().set_pose(sapien.Pose([0.5, 0, 0]))
    cam = scene.add_camera("probe", 84, 84, 1.57, 0.001, 2.0)
    t0 = time.perf_counter()
    scene.update_render()
    cam.take_picture()
    names = cam.get_picture_names()  # depends on the active shader ("default" vs ManiSkill's "minimal")
    rgb = cam.get_picture("Color")
    pos = cam.get_picture("Position" if "Position" in names else "PositionSegmentation")
    dt = time.perf_counter() - t0
    depth = -float(pos[42, 42, 2])
    if np.issubdtype(pos.dtype, np.integer):  # the minimal shader stores millimetres
        depth /= 1000.0
    return dict(
        ok=bool(rgb[42, 42, 0] > 0.5 and abs(depth - 0.4) < 0.01),
        first_frame_s=round(dt, 3),
        centre_depth_m=round(float(depth), 4),
    )


def diagnose() -> dict:
    report: dict = dict(python=platform.python_version(), platform=platform.platform())
    for pkg in ("maniskill-irb120", "mani-skill", "sapien", "torch", "gymnasium", "xacro"):
        try:
            report[f"version_{pkg}"] = md.version(pkg)
        except md.PackageNotFoundError:
            report[f"version_{pkg}"] = None
    import torch

    report["torch_cuda"] = torch.cuda.is_available()
    report["cuda_sim_available"] = False
    try:
        import sapien

        report["devices"] = _devices(sapien.render.get_device_summary())
    except Exception as e:  # noqa: BLE001 - any failure here is the diagnosis
        report["devices"] = []
        report["device_error"] = repr(e)
    if report["torch_cuda"]:
        try:
            import sapien

            sapien.physx.enable_gpu()
            report["cuda_sim_available"] = True
        except Exception as e:  # noqa: BLE001
            report["cuda_sim_error"] = repr(e)
    usable = [d for d in report["devices"] if d["supported"]]
    report["render_device"] = usable[0] if usable else None
    report["render_probe"] = None
    if usable:
        try:
            report["render_probe"] = _render_probe()
        except Exception as e:  # noqa: BLE001
            report["render_probe"] = dict(ok=False, error=repr(e))
    report["render_ok"] = bool(report["render_probe"] and report["render_probe"]["ok"])
    return report


def format_report(r: dict) -> str:
    lines = ["maniskill-irb120 doctor", f"  python {r['python']} on {r['platform']}"]
    for k, v in r.items():
        if k.startswith("version_"):
            lines.append(f"  {k[8:]:<18} {v or 'NOT INSTALLED'}")
    for d in r["devices"]:
        kind = "CPU (software)" if d["cpu"] else "GPU"
        lines.append(f"  vulkan device      {d['name']} [{kind}] supported={d['supported']}")
    if not r["devices"]:
        lines.append(f"  vulkan device      none found {r.get('device_error', '')}")
    if r["render_probe"]:
        lines.append(f"  render probe       {r['render_probe']}")
    lines.append(f"  torch CUDA         {r['torch_cuda']}")
    lines.append(f"  CUDA sim (physx)   {r['cuda_sim_available']}")
    if r.get("cuda_sim_error"):
        from maniskill_irb120.maniskill_compat import physx_gpu_library

        path, url = physx_gpu_library()
        lines.append(f"  CUDA sim error     {r['cuda_sim_error'][:200]}")
        lines.append(f"  CUDA sim needs     {path} (without internet access: unzip {url} into {path.parent})")
    if r["render_ok"]:
        dev = r["render_device"]
        where = "CPU (lavapipe/llvmpipe: fine for num_envs=1 and process-parallel envs)" if dev["cpu"] else "GPU"
        lines.append(
            f"VERDICT: OK - rendering works on {dev['name']} [{where}]"
            + ("; GPU-batched sim available" if r["cuda_sim_available"] else "; GPU-batched sim not available")
        )
    else:
        lines.append("VERDICT: FAIL - " + FIX_HINT)
    return "\n".join(lines)


def main(json_output: bool = False, json_path: str | None = None) -> int:
    """Diagnose rendering and simulation support; exit code 0 when rendering works."""
    import json

    r = diagnose()
    print(json.dumps(r, indent=2) if json_output else format_report(r))
    if json_path:
        _write_json(json_path, r)
    return 0 if r["render_ok"] else 1


# ------------------------------------------------------------------ doctor --gpu: the acceptance suite's report
NO_CUDA = (
    "doctor --gpu: no CUDA device: torch.cuda.is_available() is False here, so the GPU path (physx_cuda, batched "
    "rendering, --backend gpu trainers) cannot run. On a machine with an NVIDIA GPU install its driver and a CUDA "
    "build of torch (scripts/setup.sh picks one when nvidia-smi works), then run this again."
)
THROUGHPUT_ENVS = (512, 1024, 4096)
PROGRAM = "program"
"""a report unit that is one of ``gpu_report``'s ``programs`` (not a function of acceptance_runs)"""
CHECKOUT_PROGRAMS = (
    "the trainers' tiny --backend gpu runs and the benchmark's GPU sweep are a source checkout's programs; "
    "there, python -m benchmarks.gpu_acceptance runs this report with them added"
)


def _driver_version() -> str | None:
    """The NVIDIA driver (torch reports the CUDA runtime it was built with, not the driver)."""
    import subprocess

    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        )
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip().splitlines()[0]
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        m = re.search(r"Kernel Module\s+([\d.]+)", open("/proc/driver/nvidia/version").read())
        return m.group(1) if m else None
    except OSError:
        return None


def gpu_environment(commit: str | None = None) -> dict:
    """What a GPU report must name so that a failure can be reproduced: the device, driver and versions.
    ``commit``: the source checkout's, which only a checkout's script knows (an installed package has its version)."""
    import torch

    env: dict = dict(python=platform.python_version(), platform=platform.platform(), commit=commit)
    for pkg in ("maniskill-irb120", "mani-skill", "sapien", "torch"):
        try:
            env[f"version_{pkg}"] = md.version(pkg)
        except md.PackageNotFoundError:
            env[f"version_{pkg}"] = None
    env["cuda_runtime"] = torch.version.cuda
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        env.update(device=props.name, device_memory_gib=round(props.total_memory / 2**30, 1), driver=_driver_version())
    else:
        env.update(device=None, device_memory_gib=None, driver=_driver_version())
    return env


def gpu_report(
    sim_backend: str = "physx_cuda",
    num_envs: int = 512,
    trainer_envs: int = 64,
    checks: tuple[str, ...] | None = None,
    throughput_envs: tuple[int, ...] = THROUGHPUT_ENVS,
    throughput_steps: int = 50,
    isolate: bool = True,
    say=None,
    jobs: int = 1,
    env_ids: tuple[str, ...] | None = None,
    obs_modes: tuple[str, ...] | None = None,
    programs: Mapping[str, Callable[..., tuple[bool | None, str]]] | None = None,
    commit: str | None = None,
) -> dict:
    """Run the acceptance suite (``maniskill_irb120.diagnostics.acceptance``) and time state-obs steps/s per batch size.
    ``isolate``: each check and timing in a fresh process, so a GPU crash is one FAIL, not the end of the report.
    ``programs``: checks that start programs of their own, by name, reported after the package's checks (a source
    checkout's ``benchmarks/gpu_acceptance.py`` passes the trainers' and the benchmark's runs: the package cannot
    start them, an installed wheel has neither); each is called as ``fn(sim_backend=..., num_envs=trainer_envs)``
    in a thread of this process (its own program is its isolation) and, like the others, skipped without PhysX's
    GPU library. ``trainer_envs`` is recorded only with programs (``None`` without: nothing ran at that size).
    ``commit``: the checkout's commit, for the report's environment.
    The tests run it on ``physx_cpu`` with one env and ``isolate=False``. ``say``: called with a line as each
    check ends (the whole run takes minutes). ``jobs`` > 1 (needs ``isolate``): that many checks side by side,
    the obs-mode sweep split into one process per task and mode (a GPU machine's cores and memory take them;
    one after another the sweep alone builds 24 scenes of ``num_envs``); the steps/s are timed afterwards, alone.
    ``env_ids`` / ``obs_modes``: narrow the obs-mode sweep (default: every task, every mode)."""
    from concurrent.futures import ThreadPoolExecutor

    from maniskill_irb120.diagnostics import acceptance_runs as runs
    from maniskill_irb120.diagnostics.acceptance import ENV_IDS, OBS_MODES, timed_check
    from maniskill_irb120.diagnostics.acceptance_runs import (
        CHECK_NAMES,
        PHYSX_GPU,
        WITHOUT_PHYSX_GPU,
        isolated,
        measure_batched,
        merge_parts,
    )
    from maniskill_irb120.envs.table_clearing import ENV_ID

    programs = dict(programs or {})
    valid = (*CHECK_NAMES, *programs)
    clash = [p for p in programs if p in CHECK_NAMES]
    if clash:
        raise ValueError(f"programs {clash} have the names of the package's own checks; name them apart")
    names = valid if checks is None else checks
    unknown = [c for c in names if c not in valid]
    if unknown:
        raise ValueError(f"unknown checks {unknown}; expected some of {list(valid)}")
    if jobs < 1 or (jobs > 1 and not isolate):
        raise ValueError(f"jobs={jobs}: expected 1, or more with isolate=True (checks side by side in processes)")
    env_ids = ENV_IDS if env_ids is None else tuple(env_ids)
    obs_modes = OBS_MODES if obs_modes is None else tuple(obs_modes)
    for given, known, what in ((env_ids, ENV_IDS, "env_ids"), (obs_modes, OBS_MODES, "obs_modes")):
        if not given or [x for x in given if x not in known]:
            raise ValueError(f"{what}={list(given)}: expected some of {list(known)}")
    report: dict = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        sim_backend=sim_backend,
        num_envs=num_envs,
        trainer_envs=trainer_envs if programs else None,
        jobs=jobs,
        environment=gpu_environment(commit),
        checks=[],
        throughput=[],
    )
    mod = "maniskill_irb120.diagnostics.acceptance_runs"
    base = dict(sim_backend=sim_backend, num_envs=num_envs)

    def one(fn: str, kw: dict, name: str) -> tuple[dict, float, float]:
        t0 = time.perf_counter()
        try:
            if fn == PROGRAM:  # it starts its own process: a crash there is its FAIL already
                result = timed_check(name, programs[name], sim_backend=sim_backend, num_envs=trainer_envs).to_dict()
            elif isolate:  # 1200 s: the obs-mode sweep in one process builds 24 GPU scenes of num_envs each
                result = isolated(mod, fn, timeout_s=1200, **kw)
            else:
                result = getattr(runs, fn)(**kw)
        except RuntimeError as e:
            result = dict(name=name, ok=False, status="FAIL", reason=str(e).splitlines()[0], seconds=0.0)
        if say is not None:
            took = f"({result['seconds']:.0f} s)"
            say(f"[doctor --gpu] {result['name']}: {result['status']} {took} {result['reason'][:300]}")
        return result, t0, time.perf_counter()

    if PHYSX_GPU in names:  # first and alone: without it every physx_cuda check would fail the same way
        first, _, _ = one("run_named_check", dict(base, name=PHYSX_GPU), PHYSX_GPU)
        report["checks"].append(first)
        names = tuple(n for n in names if n != PHYSX_GPU)
        if first["ok"] is False:
            why = f"not run: PhysX's GPU library is not available ({PHYSX_GPU}, above)"
            for n in names:
                if n in WITHOUT_PHYSX_GPU:
                    report["checks"].append(one("run_named_check", dict(base, name=n), n)[0])
                else:
                    report["checks"].append(dict(name=n, ok=None, status="SKIP", reason=why, seconds=0.0))
            report["throughput"] = [dict(num_envs=n, error=f"not run ({PHYSX_GPU})") for n in throughput_envs]
            report["ok"] = False
            return report
    split = "obs modes" in names and (jobs > 1 or (env_ids, obs_modes) != (ENV_IDS, OBS_MODES))
    units: list[tuple[str, str, dict]] = []  # (the check it belongs to, function, its arguments)
    for name in names:
        if name == "obs modes" and split:
            parts = [dict(base, env_id=e, obs_mode=m) for e in env_ids for m in obs_modes]
            units += [(name, "run_obs_mode_check", kw) for kw in parts]
        elif name in programs:
            units.append((name, PROGRAM, {}))
        else:
            units.append((name, "run_named_check", dict(base, name=name)))
    if jobs == 1:  # in this thread: the in-process path (isolate=False) builds its envs here
        done = [one(fn, kw, name) for name, fn, kw in units]
    else:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            done = list(pool.map(lambda u: one(u[1], u[2], u[0]), units))
    for name in names:
        mine = [d for u, d in zip(units, done) if u[0] == name]
        if name == "obs modes" and split:
            wall = max(end for _, _, end in mine) - min(start for _, start, _ in mine)
            report["checks"].append(merge_parts(name, [r for r, _, _ in mine], wall))
        else:
            report["checks"].append(mine[0][0])
    backend = "gpu" if "cuda" in sim_backend else "inprocess"
    for n in throughput_envs:
        kw = dict(env_id=ENV_ID, num_envs=n, steps=throughput_steps, seed=0, backend=backend, obs_mode="state")
        try:
            row = isolated(mod, "measure_batched", **kw) if isolate else measure_batched(**kw)
        except Exception as e:  # noqa: BLE001 - the row says what failed
            row = dict(num_envs=n, error=f"{type(e).__name__}: {str(e).strip().splitlines()[0][:200]}")
        report["throughput"].append(row)
        if say is not None:
            say(f"[doctor --gpu] steps/s at {n} envs: {row.get('env_steps_per_s', row.get('error'))}")
    report["ok"] = all(c["ok"] is not False for c in report["checks"]) and not any(
        "error" in r for r in report["throughput"]
    )
    return report


def format_gpu_report(r: dict) -> str:
    """The report as plain text, one line per fact, short enough to paste into an issue."""
    env = r["environment"]
    mem = f" ({env['device_memory_gib']} GiB)" if env.get("device_memory_gib") else ""
    lines = [
        f"maniskill-irb120 doctor --gpu, {r['date']}",
        f"  device             {env.get('device') or 'none'}{mem}",
        f"  driver             {env.get('driver') or 'unknown'}",
        f"  CUDA (torch build) {env.get('cuda_runtime') or 'none'}",
    ]
    for k, v in env.items():
        if k.startswith("version_"):
            lines.append(f"  {k[8:]:<18} {v or 'NOT INSTALLED'}")
    lines.append(f"  commit             {env.get('commit') or 'unknown'}")
    lines.append(f"  python             {env['python']} on {env['platform']}")
    trainers = f"; trainers num_envs={r['trainer_envs']}" if r["trainer_envs"] is not None else ""
    lines.append(f"checks ({r['sim_backend']}, num_envs={r['num_envs']}{trainers}):")
    for c in r["checks"]:
        lines.append(f"  {c['status']:<4}  {c['name']:<24} {c['reason']} [{c['seconds']:.0f} s]")
    if r["trainer_envs"] is None:
        lines.append(f"  not run here: {CHECKOUT_PROGRAMS}")
    if r["throughput"]:
        lines.append("steps/s (TableClearing-IRB120-v1, state obs, random actions, auto-reset):")
        for t in r["throughput"]:
            if "error" in t:
                lines.append(f"  num_envs={t['num_envs']:<6} FAIL {t['error']}")
            else:
                mem = f", GPU memory {t['gpu_mem_used_gb']:.1f} GB" if t.get("gpu_mem_used_gb") else ""
                lines.append(f"  num_envs={t['num_envs']:<6} {t['env_steps_per_s']:.0f} env steps/s{mem}")
    failed = [c["name"] for c in r["checks"] if c["ok"] is False]
    failed += [f"steps/s at {t['num_envs']}" for t in r["throughput"] if "error" in t]
    passed = f"PASS - every check passed on {r['sim_backend']}"
    lines.append("VERDICT: " + (passed if r["ok"] else f"FAIL - {', '.join(failed)}"))
    return "\n".join(lines)


def gpu_main(
    json_output: bool = False,
    json_path: str | None = None,
    jobs: int = 1,
    programs: Mapping[str, Callable[..., tuple[bool | None, str]]] | None = None,
    trainer_envs: int = 64,
    commit: str | None = None,
) -> int:
    """``doctor --gpu``: 0 when every check passes, 1 when one fails, 2 without a CUDA device. ``programs``,
    ``trainer_envs``, ``commit``: as :func:`gpu_report` (a source checkout's ``benchmarks/gpu_acceptance.py``)."""
    import json
    import sys

    import torch

    if not torch.cuda.is_available():
        print(NO_CUDA, file=sys.stderr)
        return 2
    say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    r = gpu_report(say=say, jobs=jobs, programs=programs, trainer_envs=trainer_envs, commit=commit)
    print(json.dumps(r, indent=2) if json_output else format_gpu_report(r))
    if json_path:
        _write_json(json_path, r)
    return 0 if r["ok"] else 1


def _write_json(path: str, report: dict) -> None:
    import json
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(report, indent=2))
