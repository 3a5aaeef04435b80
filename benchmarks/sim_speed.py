"""Simulator benchmark: the original report's Table 5.1 for TableClearing-IRB120-v1, with references from the same run.

Modes (the original report's): ``render_realtime`` (84x84 RGB-D hand camera every action, paced to real time),
``render`` (camera every action, as fast as possible), ``no_render`` (state observations, no camera).
References measured in the same run, so results are ratios on one machine:

1. ManiSkill's ``PickCube-v1`` with its camera at 84x84 RGB-D (the peer a user would pick instead);
2. the original report's own action loop re-implemented in PyBullet (``benchmarks/lib/pybullet_loop.py``).

Each configuration runs in a fresh process (clean peak memory, no shared renderer state). Actions are
the same seeded uniform random actions for every simulator; episodes that end are reset, untimed.

    python -m benchmarks.sim_speed                       # full run (~5 min on 2 cores)
    python -m benchmarks.sim_speed --quick --json out.json
    python -m benchmarks.sim_speed --baseline HEAD~3      # also an earlier commit's code, in the same rounds

``--baseline REF`` measures the task at another commit of this repository beside this checkout's, configuration by
configuration in the same rounds, so that a change's speed-up is a ratio from one run rather than two runs minutes
apart on a machine that drifts (the other commit's Python code; the robot assets are the installed ones).
"""

from __future__ import annotations

import importlib.util
import json
import multiprocessing as mp
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.pybullet_loop import random_actions
from benchmarks.lib.report import argv_command, linked_path, raw_link, recorded_command, replace_section

HERE = Path(__file__).resolve().parent

ENV_ID = "TableClearing-IRB120-v1"
MODES = ("render_realtime", "render", "no_render")
SPLIT = ("physics", "controller", "evaluate", "reward", "observation", "render")
"""where an action's time goes: PhysX's substeps, the agent's set_action (controller and IK), the task's evaluate
(events and reward terms), the reward, the observation's agent and extra parts (state observations included), and
the camera frame's capture and read-back; the rest of ``env.step`` is ManiSkill's plumbing and the wrappers"""
BASELINE_MODES = ("render", "no_render")
"""the modes measured at the --baseline commit too (real time is paced, so it shows no code's speed)"""


def summarize(times) -> dict:
    t = np.asarray(times, dtype=float)
    q = np.percentile(t, [25, 50, 75])
    return dict(
        n=int(t.size),
        mean=float(t.mean()),
        std=float(t.std()),
        min=float(t.min()),
        p25=float(q[0]),
        p50=float(q[1]),
        p75=float(q[2]),
        max=float(t.max()),
        steps_per_s=float(t.size / t.sum()),
    )


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(obj, name: str, acc: dict, key: str) -> None:
    fn = getattr(obj, name)

    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            acc[key] += time.perf_counter() - t0

    setattr(obj, name, wrapper)


def measure_maniskill(env_id: str, mode: str, steps: int, seed: int, warmup: int = 10, **kwargs) -> dict:
    """Per-action wall time of one ManiSkill env on CPU, with the physics/controller/render/Python split.

    The split wraps ``scene.step`` (physics), ``agent.set_action`` (controller incl. IK) and
    ``_get_obs_sensor_data`` (camera capture and read-back); the rest of ``env.step`` is Python/other
    (evaluation, reward, observation assembly). Resets are excluded from both. TableClearing starts its
    frame right after physics (``render_ahead``), so its "rendering" is the wait for and read-back of a
    frame drawn while ``evaluate`` ran, and the frame's start (~0.1 ms) counts as Python/other.
    """
    import gymnasium as gym
    import torch

    import maniskill_irb120  # noqa: F401

    torch.set_num_threads(1)
    obs_mode = "state" if mode == "no_render" else "rgbd"
    extra = dict(render_backend="none") if mode == "no_render" else {}
    t_make = time.perf_counter()
    env = gym.make(env_id, obs_mode=obs_mode, **extra, **kwargs)
    u = env.unwrapped
    env.reset(seed=seed)
    make_s = time.perf_counter() - t_make
    acc = dict.fromkeys(SPLIT, 0.0)
    _timed(u.scene, "step", acc, "physics")
    _timed(u.agent, "set_action", acc, "controller")
    _timed(u, "evaluate", acc, "evaluate")
    _timed(u, "get_reward", acc, "reward")
    _timed(u, "_get_obs_agent", acc, "observation")
    _timed(u, "_get_obs_extra", acc, "observation")
    if obs_mode != "state":
        _timed(u, "_get_obs_sensor_data", acc, "render")
    acts = random_actions(steps + warmup, seed, env.action_space.shape[-1]).astype(np.float32)
    dt_real = 1.0 / u.control_freq
    times, resets = [], 0
    for i, a in enumerate(acts):
        if i == warmup:
            acc.update(dict.fromkeys(SPLIT, 0.0))
        t0 = time.perf_counter()
        _, _, term, trunc, _ = env.step(a)
        if mode == "render_realtime":  # the sim advances dt_real per action: do not run ahead of the clock
            rest = dt_real - (time.perf_counter() - t0)
            if rest > 0:
                time.sleep(rest)
        if i >= warmup:
            times.append(time.perf_counter() - t0)
        if bool(term) or bool(trunc):
            saved = dict(acc)
            env.reset()
            acc.update(saved)
            resets += 1
    env.close()
    split = {k: v / len(times) for k, v in acc.items()}
    busy = sum(times) / len(times) if mode != "render_realtime" else None
    split["python"] = (busy - sum(split.values())) if busy is not None else float("nan")
    return dict(times=times, resets=resets, make_s=make_s, peak_rss_mb=peak_rss_mb(), split_s=split)


def measure_floor(env_id: str, steps: int, seed: int, warmup: int = 10) -> dict:
    """The physics + frame floor: what one rgbd action must cost at least on this machine, without ManiSkill's
    Python layer. The same scene (built by the task), straight SAPIEN calls: the control period's physics
    substeps on the PhysX system, then one hand-camera frame drawn and both pictures (colour, position/depth)
    read back. The robot holds still (no controller, no IK): the floor of the physics, not of a motion."""
    import gymnasium as gym
    import torch

    import maniskill_irb120  # noqa: F401

    torch.set_num_threads(1)
    env = gym.make(env_id, obs_mode="rgbd")
    u = env.unwrapped
    env.reset(seed=seed)
    cam = u._sensors["hand_camera"].camera._render_cameras[0]
    sub, px = u.scene.sub_scenes[0], u.scene.px
    substeps = u.sim_freq // u.control_freq
    pictures = [n for n in ("Color", "PositionSegmentation", "Position") if n in cam.get_picture_names()][:2]
    times = []
    for i in range(steps + warmup):
        t0 = time.perf_counter()
        for _ in range(substeps):
            px.step()
        sub.update_render()
        cam.take_picture()
        for name in pictures:
            cam.get_picture(name)
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    env.close()
    return dict(times=times, substeps=substeps, pictures=pictures)


# the CPU vector-env configurations measured side by side: (name, envs, vector env); "one" and "two" are what
# make_vec_env gives a trainer (one env: in this process; two: env 0 here, env 1 in a worker), the others the
# all-in-workers layout (CPUVectorEnv local_first=False) that two envs had before
SCALING = (("one", 1, "inprocess"), ("one_worker", 1, "workers"), ("two", 2, "cpu"), ("two_workers", 2, "workers"))


def measure_scaling(env_id: str, steps: int, seed: int, obs_mode: str = "rgbd", blocks: int = 4) -> dict:
    """Aggregate env steps/s of the CPU vector-env configurations (``SCALING``), all built in this process and
    stepped in turns, ``blocks`` blocks of ``steps // blocks`` batched steps each: the machine's drift, which moves
    whole minutes (docs/notes/sim-speed.md), then lands on every configuration alike instead of on whichever ran later.
    Idle workers sleep on their pipes. Per configuration also this process's CPU time per batched step (what the
    workers wait for while it gathers their results)."""
    import torch

    from maniskill_irb120.vector import CPUVectorEnv, make_vec_env

    torch.set_num_threads(1)  # as the trainers run beside CPU workers (agents.common.one_thread_beside_workers)
    extra = dict(render_backend="none") if obs_mode == "state" else {}
    envs = {}
    for name, n, kind in SCALING:
        if kind == "workers":
            envs[name] = CPUVectorEnv(env_id, n, obs_mode=obs_mode, local_first=False, **extra)
        else:
            envs[name] = make_vec_env(env_id, n, backend=kind, obs_mode=obs_mode, record_metrics=False, **extra)
    acts = torch.from_numpy(random_actions(steps + 5, seed, 10).astype(np.float32).reshape(-1, 2, 5))
    per = max(1, steps // blocks)
    wall = {k: 0.0 for k in envs}
    cpu = {k: 0.0 for k in envs}
    for env in envs.values():
        env.reset(seed=seed)
        for a in acts[:5]:
            env.step(a[: env.num_envs])
    for b in range(blocks):
        for name, env in envs.items():
            chunk = acts[5 + b * per : 5 + (b + 1) * per]
            t0, c0 = time.perf_counter(), time.process_time()
            for a in chunk:
                env.step(a[: env.num_envs])
            wall[name] += time.perf_counter() - t0
            cpu[name] += time.process_time() - c0
    for env in envs.values():
        env.close()
    n_steps = per * blocks
    return dict(
        obs_mode=obs_mode,
        steps=n_steps,
        configs={
            name: dict(
                envs=n,
                layout=kind,
                env_steps_per_s=n_steps * n / wall[name],
                main_cpu_ms_per_step=1e3 * cpu[name] / n_steps,
            )
            for name, n, kind in SCALING
        },
        peak_rss_mb=peak_rss_mb(),
    )


def _burn(n: int) -> float:
    t0, acc = time.perf_counter(), 0
    for i in range(n):
        acc += i * i
    return time.perf_counter() - t0


def measure_parallel_ceiling(n: int = 5_000_000) -> dict:
    """How well this machine runs two CPU-bound processes at once (pure Python, no I/O): the upper
    bound for any 2-worker speed-up here (shared or throttled vCPUs score below 2.0)."""
    one = _burn(n)
    ctx = mp.get_context("spawn")
    with ctx.Pool(2) as pool:
        pool.map(_burn, [1000, 1000])  # start-up outside the timing
        t0 = time.perf_counter()
        pool.map(_burn, [n, n])
        two = time.perf_counter() - t0
    return dict(one_s=one, two_parallel_s=two, speedup=2 * one / two)


def measure_batched(
    env_id: str, num_envs: int, steps: int, seed: int, backend: str = "gpu", obs_mode: str = "rgbd"
) -> dict:
    """The GPU sweep's measurement, shared with ``maniskill-irb120 doctor --gpu`` (imported here, not at the top:
    the PyBullet and CPU configurations' processes must not load ManiSkill)."""
    from maniskill_irb120.diagnostics.acceptance_runs import measure_batched as measure

    return measure(env_id, num_envs, steps, seed, backend=backend, obs_mode=obs_mode)


def measure_pybullet(mode: str, steps: int, seed: int) -> dict:
    from benchmarks.lib import pybullet_loop

    r = pybullet_loop.measure(mode, steps, seed)
    return dict(
        times=r["times"], resets=r.get("collided", 0), peak_rss_mb=peak_rss_mb(), mean_substeps=r.get("mean_substeps")
    )


def import_package_from(tree: str, name: str = "maniskill_irb120") -> None:
    """Import ``name`` from the source tree ``tree`` (another commit's): its submodules, which the measurement imports
    later, then resolve through the package's own ``__path__`` in that tree, with ``sys.path`` left alone."""
    init = Path(tree) / name / "__init__.py"
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


def _run(conn, fn: str, kwargs: dict, tree: Optional[str] = None) -> None:
    if tree is not None:  # another commit's package in place of this checkout's (imported inside the measurement)
        import_package_from(tree)
    try:
        conn.send(("ok", globals()[fn](**kwargs)))
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which re-raises
        import traceback

        conn.send(("error", f"{fn}({kwargs}) failed:\n{traceback.format_exc()}"))
        raise SystemExit(1) from e


ISOLATE = True


def isolated(fn: str, tree: Optional[str] = None, **kwargs) -> dict:
    """Run one measurement in a fresh (non-daemonic: it may start workers) process; ``tree``: a source tree whose
    ``maniskill_irb120`` it imports instead of this checkout's (always a fresh process)."""
    if not ISOLATE and tree is None:  # --quick: one process, imports paid once
        return globals()[fn](**kwargs)
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_run, args=(child, fn, kwargs, tree))
    proc.start()
    child.close()
    try:
        status, value = parent.recv()
    except EOFError:
        raise RuntimeError(f"{fn} died without a result (exit code {proc.join() or proc.exitcode})") from None
    proc.join()
    if status != "ok":
        raise RuntimeError(value)
    return value


@dataclass
class Args:
    steps: int = 300
    """timed actions per configuration (realtime mode uses a quarter)"""
    seed: int = 0
    rounds: int = 3
    """interleaved repetitions of the whole suite; ratios are the median over rounds (VMs drift)"""
    quick: bool = False
    """a smoke run: one round, few actions per configuration, in one process, no GPU sweep (~1 min)"""
    json: Optional[Path] = None
    plot: Optional[Path] = None
    gpu_num_envs: tuple[int, ...] = (16, 64, 256, 1024, 4096)
    gpu_steps: int = 300
    """timed batched steps per num_envs in the GPU sweep (auto-reset, fresh random actions each step)"""
    gpu_only: bool = False
    """run only the GPU sweep (skips the CPU / PyBullet suite; needs CUDA)"""
    baseline: Optional[str] = None
    """a git ref of this repository (e.g. main, HEAD~3, a commit): its code is measured beside this checkout's in
    every round (modes render and no_render), and the JSON gets its rates and this code's speed-up over it"""
    update_results: bool = False
    """rewrite the Simulator speed section of benchmarks/RESULTS.md from this run (needs --json)"""
    note: str = ""
    """what else ran on the machine during the run, for the RESULTS section (a wall-clock figure needs it)"""
    render_only: bool = False
    """rewrite the RESULTS section from the JSON (--json, else the committed one), measuring nothing"""


def fmt_row(name: str, s: dict) -> str:
    return (
        f"| {name} | {s['mean']:.4f} | {s['std']:.4f} | {s['min']:.4f} | {s['p25']:.4f} | {s['p50']:.4f} | "
        f"{s['p75']:.4f} | {s['max']:.4f} | {s['steps_per_s']:.1f} |"
    )


def one_round(args: Args, steps: int, baseline_tree: Optional[str] = None) -> dict:
    """Every configuration once, back to back (a round); rounds are interleaved against drift."""
    rt_steps = max(10, steps // 4)
    r: dict = dict(ours={}, pyb={}, base={})
    for mode in MODES:
        n = rt_steps if mode == "render_realtime" else steps
        r["ours"][mode] = isolated("measure_maniskill", env_id=ENV_ID, mode=mode, steps=n, seed=args.seed)
        if baseline_tree is not None and mode in BASELINE_MODES:
            r["base"][mode] = isolated(
                "measure_maniskill", tree=baseline_tree, env_id=ENV_ID, mode=mode, steps=n, seed=args.seed
            )
        r["pyb"][mode] = isolated("measure_pybullet", mode=mode, steps=n, seed=args.seed)
    r["pick"] = isolated(
        "measure_maniskill",
        env_id="PickCube-v1",
        mode="render",
        steps=steps,
        seed=args.seed,
        sensor_configs=dict(width=84, height=84),
    )
    r["scaling"] = {
        mode: isolated("measure_scaling", env_id=ENV_ID, steps=max(8, steps), seed=args.seed, obs_mode=mode)
        for mode in ("rgbd", "state")
    }
    r["floor"] = isolated("measure_floor", env_id=ENV_ID, steps=steps, seed=args.seed)
    r["ceiling"] = measure_parallel_ceiling(1_000_000 if args.quick else 5_000_000)
    rate = lambda x: len(x["times"]) / sum(x["times"])  # noqa: E731
    r["ratios"] = dict(
        vs_pickcube_rgbd=rate(r["ours"]["render"]) / rate(r["pick"]),
        vs_pybullet_original={m: rate(r["ours"][m]) / rate(r["pyb"][m]) for m in MODES},
        **{
            f"{key}{suffix}": scaling_ratio(r["scaling"][mode]["configs"], a, b)
            for mode, suffix in (("rgbd", ""), ("state", "_state"))
            for key, (a, b) in SCALING_RATIOS.items()
        },
        rgbd_fraction_of_floor=rate(r["ours"]["render"]) / rate(r["floor"]),
        machine_two_process_ceiling=r["ceiling"]["speedup"],
    )
    if r["base"]:
        r["ratios"]["vs_baseline"] = {m: rate(r["ours"][m]) / rate(r["base"][m]) for m in r["base"]}
        r["ratios"]["baseline_vs_pybullet_original"] = {m: rate(r["base"][m]) / rate(r["pyb"][m]) for m in r["base"]}
    return r


def commit_of(ref: str) -> str:
    """The commit a git ref of this repository names; a ref git does not know is a ValueError naming --baseline."""
    import subprocess

    try:
        return subprocess.run(
            ["git", "rev-parse", "--verify", f"{ref}^{{commit}}"],
            cwd=HERE.parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as e:
        raise ValueError(f"--baseline {ref!r}: not a commit of this repository ({e})") from None


def baseline_tree(ref: str, into: Path) -> str:
    """The commit ``ref`` names, and its files (``git archive``) unpacked under ``into``; a ref git does not know is a
    SystemExit naming it."""
    import subprocess
    import tarfile

    try:
        commit = commit_of(ref)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    archive = into / "tree.tar"
    with archive.open("wb") as f:
        subprocess.run(["git", "archive", "--format=tar", commit], cwd=HERE.parent, stdout=f, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "tree", filter="data")
    return commit


# ratio name -> (configuration, reference configuration) of SCALING
SCALING_RATIOS = {
    "two_envs_vs_one": ("two", "one"),
    "two_workers_vs_one": ("two_workers", "one_worker"),
    "env_zero_here_vs_all_in_workers": ("two", "two_workers"),
}


def scaling_ratio(configs: dict, a: str, b: str) -> float:
    return configs[a]["env_steps_per_s"] / configs[b]["env_steps_per_s"]


def gpu_sweep(args: Args) -> list[dict]:
    return [
        isolated("measure_batched", env_id=ENV_ID, num_envs=n, steps=args.gpu_steps, seed=args.seed)
        for n in args.gpu_num_envs
    ]


RESULTS_JSON = HERE / "results" / "sim_speed.json"
RESULTS_PLOT = HERE / "results" / "sim_speed.png"


def update_results(json_path: Path, results: Path = HERE / "RESULTS.md") -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path`` (its plot beside it)."""
    plot_path = json_path.with_suffix(".png")
    replace_section(
        results,
        RESULTS_HEAD,
        results_section(json.loads(json_path.read_text()), json_path, plot_path if plot_path.is_file() else None),
    )


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any measurement (``benchmarks.lib.cli`` makes it one
    line and exit status 2): --render-only with a JSON that is not there, --steps, --rounds, --gpu-steps or a
    --gpu-num-envs below 1, --gpu-only without CUDA, a --baseline that is no commit of this repository."""
    if args.render_only:
        rendered_from(args.json or RESULTS_JSON, "--json")
        return
    for flag, value in (("--steps", args.steps), ("--rounds", args.rounds), ("--gpu-steps", args.gpu_steps)):
        if value < 1:
            raise ValueError(f"{flag} {value}: expected 1 or more")
    if not args.gpu_num_envs or min(args.gpu_num_envs) < 1:
        raise ValueError(f"--gpu-num-envs {list(args.gpu_num_envs)}: give one or more counts, each 1 or more")
    if args.gpu_only:
        import torch

        if not torch.cuda.is_available():
            raise ValueError("--gpu-only needs CUDA; none is available here")
    if args.baseline is not None:
        commit_of(args.baseline)


def main(args: Args) -> dict:
    global ISOLATE
    check(args)
    if args.render_only:
        update_results(args.json or RESULTS_JSON)
        return json.loads((args.json or RESULTS_JSON).read_text())
    ISOLATE = not args.quick
    if args.gpu_only:
        import torch

        out = dict(
            date=time.strftime("%Y-%m-%d %H:%M:%S"),
            command=" ".join(sys.argv),
            device=torch.cuda.get_device_name(),
            gpu_scaling=gpu_sweep(args),
        )
        print(gpu_markdown(out["gpu_scaling"]))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=2))
        return out
    if args.update_results:  # the section shows the committed JSON and the plot beside it
        args.json = args.json or RESULTS_JSON
        args.plot = args.plot or args.json.with_suffix(".png")
    steps = 12 if args.quick else args.steps
    rounds = 1 if args.quick else args.rounds
    out: dict = dict(
        machine=dict(
            platform=platform.platform(),
            python=platform.python_version(),
            cpus=os.cpu_count(),
            processor=platform.processor(),
        ),
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=argv_command("benchmarks.sim_speed", sys.argv[1:]),
        note=args.note,
        steps=steps,
        rounds=rounds,
    )
    with tempfile.TemporaryDirectory(prefix="sim_speed_baseline_") as tmp:
        base = None
        if args.baseline is not None:
            base = dict(ref=args.baseline, commit=baseline_tree(args.baseline, Path(tmp)))
        runs = [one_round(args, steps, str(Path(tmp) / "tree") if base else None) for _ in range(rounds)]
    pooled = lambda get: [t for r in runs for t in get(r)["times"]]  # noqa: E731
    ours, pyb = {}, {}
    for mode in MODES:
        split = {
            k: float(np.mean([r["ours"][mode]["split_s"][k] for r in runs])) for k in runs[0]["ours"][mode]["split_s"]
        }
        ours[mode] = dict(
            summarize(pooled(lambda r, mode=mode: r["ours"][mode])),
            split_s=split,
            peak_rss_mb=max(r["ours"][mode]["peak_rss_mb"] for r in runs),
        )
        pyb[mode] = dict(
            summarize(pooled(lambda r, mode=mode: r["pyb"][mode])),
            peak_rss_mb=max(r["pyb"][mode]["peak_rss_mb"] for r in runs),
            mean_substeps=float(np.mean([r["pyb"][mode]["mean_substeps"] for r in runs])),
        )
    pick = dict(summarize(pooled(lambda r: r["pick"])), peak_rss_mb=max(r["pick"]["peak_rss_mb"] for r in runs))
    scaling = {
        mode: {
            name: dict(
                envs=runs[0]["scaling"][mode]["configs"][name]["envs"],
                layout=runs[0]["scaling"][mode]["configs"][name]["layout"],
                **{
                    k: float(np.median([r["scaling"][mode]["configs"][name][k] for r in runs]))
                    for k in ("env_steps_per_s", "main_cpu_ms_per_step")
                },
            )
            for name, *_ in SCALING
        }
        for mode in ("rgbd", "state")
    }
    med = lambda f: float(np.median([f(r["ratios"]) for r in runs]))  # noqa: E731
    ratios = dict(
        vs_pickcube_rgbd=med(lambda x: x["vs_pickcube_rgbd"]),
        vs_pybullet_original={m: med(lambda x, m=m: x["vs_pybullet_original"][m]) for m in MODES},
        **{
            f"{key}{suffix}": med(lambda x, k=f"{key}{suffix}": x[k])
            for key in SCALING_RATIOS
            for suffix in ("", "_state")
        },
        rgbd_fraction_of_floor=med(lambda x: x["rgbd_fraction_of_floor"]),
        machine_two_process_ceiling=med(lambda x: x["machine_two_process_ceiling"]),
    )
    if base is not None:
        for key in ("vs_baseline", "baseline_vs_pybullet_original"):
            ratios[key] = {m: med(lambda x, k=key, m=m: x[k][m]) for m in BASELINE_MODES}
        base["ours"] = {}
        for m in BASELINE_MODES:
            split = {
                k: float(np.mean([r["base"][m]["split_s"].get(k, np.nan) for r in runs])) for k in SPLIT + ("python",)
            }
            base["ours"][m] = dict(summarize(pooled(lambda r, m=m: r["base"][m])), split_s=split)
    floor = summarize(pooled(lambda r: r["floor"]))
    import torch

    gpu = gpu_sweep(args) if torch.cuda.is_available() and not args.quick else []
    out.update(
        env_steps_per_s={m: ours[m]["steps_per_s"] for m in MODES},
        reference_steps_per_s=dict(
            pickcube_rgbd_84=pick["steps_per_s"], pybullet_original={m: pyb[m]["steps_per_s"] for m in MODES}
        ),
        ratios=ratios,
        ratios_per_round=[r["ratios"] for r in runs],
        ours=ours,
        pybullet_original=pyb,
        pickcube_rgbd_84=pick,
        floor=floor,
        cpu_scaling=scaling,
        gpu_scaling=gpu,
        baseline=base,
    )
    print(markdown(out))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    if args.plot:
        plot(out, args.plot)
    if args.update_results:
        update_results(args.json)
    return out


def markdown(r: dict) -> str:
    head = (
        "| configuration | mean (s) | std | min | 25% | 50% | 75% | max | steps/s |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    rows = [head]
    for m in MODES:
        rows.append(fmt_row(f"TableClearing-IRB120-v1 (ManiSkill) — {m}", r["ours"][m]))
        rows.append(fmt_row(f"original report's loop (PyBullet) — {m}", r["pybullet_original"][m]))
    rows.append(fmt_row("PickCube-v1 (ManiSkill) — rgbd 84x84", r["pickcube_rgbd_84"]))
    rows.append(fmt_row("floor: 5 physics substeps + one RGB-D frame (SAPIEN, no ManiSkill)", r["floor"]))
    lines = [
        f"## Action time (Table 5.1 layout; {r['rounds']} interleaved rounds x {r['steps']} actions, pooled)",
        *rows,
        "",
        "## Ratios (same run; median over rounds, per-round values in the JSON)",
        f"- TableClearing rgbd vs PickCube-v1 rgbd 84x84: {r['ratios']['vs_pickcube_rgbd']:.2f}x",
    ]
    for m in MODES:
        lines.append(
            f"- TableClearing vs the original report's PyBullet loop, {m}: "
            f"{r['ratios']['vs_pybullet_original'][m]:.2f}x per action"
        )
    lines.append(
        f"- TableClearing rgbd at {100 * r['ratios']['rgbd_fraction_of_floor']:.0f} % of the physics + frame floor's "
        "speed (floor time / step time)"
    )
    for mode, suffix in (("rgbd", ""), ("state", "_state")):
        c = r["cpu_scaling"][mode]
        lines.append(
            f"- {mode}: 2 envs (env 0 here, env 1 in a worker) vs 1 env here: "
            f"{r['ratios']['two_envs_vs_one' + suffix]:.2f}x ({c['one']['env_steps_per_s']:.1f} -> "
            f"{c['two']['env_steps_per_s']:.1f} env steps/s); 2 worker processes vs 1: "
            f"{r['ratios']['two_workers_vs_one' + suffix]:.2f}x ({c['one_worker']['env_steps_per_s']:.1f} -> "
            f"{c['two_workers']['env_steps_per_s']:.1f}); env 0 here vs all in workers: "
            f"{r['ratios']['env_zero_here_vs_all_in_workers' + suffix]:.2f}x"
        )
    lines.append(
        f"- this machine's own ceiling for two CPU-bound processes: {r['ratios']['machine_two_process_ceiling']:.2f}x"
    )
    if r.get("baseline"):
        vs = r["ratios"]["vs_baseline"]
        lines.append(
            f"- this code vs the baseline commit {r['baseline']['commit'][:7]} ({r['baseline']['ref']}): "
            + ", ".join(f"{m} {vs[m]:.2f}x" for m in BASELINE_MODES)
        )
    per_round = ", ".join(f"{x['vs_pickcube_rgbd']:.2f}" for x in r["ratios_per_round"])
    lines.append(
        f"- per round, vs PickCube: {per_round}; vs PyBullet (render): "
        + ", ".join(f"{x['vs_pybullet_original']['render']:.2f}" for x in r["ratios_per_round"])
    )
    lines += [
        "",
        "## Where an action's time goes (ManiSkill, ms per action)",
        split_table(r),
    ]
    if r["gpu_scaling"]:
        lines += ["", gpu_markdown(r["gpu_scaling"])]
    return "\n".join(lines)


def split_table(r: dict) -> str:
    """Where an action's time goes (:data:`SPLIT`), ms per action, this code's and the baseline's."""
    cols = [*SPLIT, "python"]
    lines = [
        "| code | mode | " + " | ".join(c if c != "python" else "ManiSkill + wrappers" for c in cols) + " | total |",
        "|---" * (len(cols) + 3) + "|",
    ]
    rows = [("this", m, r["ours"][m]) for m in MODES if m != "render_realtime"]
    if r.get("baseline"):
        rows += [(f"baseline `{r['baseline']['commit'][:7]}`", m, r["baseline"]["ours"][m]) for m in BASELINE_MODES]
    for who, m, o in rows:
        s = o["split_s"]
        cells = " | ".join(f"{1e3 * s[c]:.2f}" if c in s and s[c] == s[c] else "" for c in cols)
        lines.append(f"| {who} | {m} | {cells} | {1e3 * o['mean']:.2f} |")
    return "\n".join(lines)


RESULTS_HEAD = "## Simulator speed — `benchmarks/sim_speed.py`"
HEAD = RESULTS_HEAD  # the name every benchmark gives its section head
# the targets the section checks (ratios from one run): name -> (ratio key, lowest acceptable value)
TARGETS = {
    "state vs the original report's PyBullet loop without a camera": (("vs_pybullet_original", "no_render"), 1.3),
    "rgbd vs the PyBullet loop with its camera": (("vs_pybullet_original", "render"), 4.0),
    "rgbd as a fraction of the physics + frame floor's speed": (("rgbd_fraction_of_floor",), 0.6),
    "rgbd vs ManiSkill's PickCube-v1 at 84x84 RGB-D": (("vs_pickcube_rgbd",), 8.0),
}


def results_section(r: dict, json_path: Path, plot_path: Optional[Path]) -> str:
    """The RESULTS.md section of one run: its command and machine note, the targets table, the speed-up over the
    baseline commit (when measured), where the time goes, and the plot."""
    ratios = r["ratios"]

    def get(keys):
        v = ratios
        for k in keys:
            v = v[k]
        return v

    lines = [
        RESULTS_HEAD,
        "",
        "*Generated by `benchmarks/sim_speed.py --update-results`.*",
        "",
        f"Command: `{recorded_command(r['command'])}`, run {r['date']}: {r['rounds']} interleaved rounds x "
        f"{r['steps']} random actions per configuration, each in a fresh process. Beside it: "
        f"{r.get('note') or 'not recorded'}. Raw data: {raw_link(json_path)} (per-round ratios in `ratios_per_round`).",
        "",
        "| ratio (median over rounds) | this run | target | |",
        "|---|---|---|---|",
    ]
    for name, (keys, target) in TARGETS.items():
        v = get(keys)
        shown = f"{100 * v:.0f} %" if keys == ("rgbd_fraction_of_floor",) else f"{v:.2f}x"
        goal = f"≥ {100 * target:.0f} %" if keys == ("rgbd_fraction_of_floor",) else f"≥ {target:g}x"
        lines.append(f"| {name} | **{shown}** | {goal} | {'met' if v >= target else 'not met'} |")
    for mode, suffix in (("state", "_state"), ("rgbd", "")):
        lines.append(
            f"| {mode}: 2 envs (env 0 here, env 1 in a worker) vs 1 env here | "
            f"{ratios['two_envs_vs_one' + suffix]:.2f}x | | |"
        )
    lines.append(
        f"| this machine's ceiling: two CPU-bound processes vs one | {ratios['machine_two_process_ceiling']:.2f}x | | |"
    )
    rates = r["env_steps_per_s"]
    lines += [
        "",
        f"One process: state {rates['no_render']:.0f} steps/s, rgbd {rates['render']:.0f} steps/s; the PyBullet loop "
        f"{r['reference_steps_per_s']['pybullet_original']['no_render']:.0f} and "
        f"{r['reference_steps_per_s']['pybullet_original']['render']:.0f}; the floor {r['floor']['steps_per_s']:.0f}.",
    ]
    if r.get("baseline"):
        b = r["baseline"]
        vs, bp = ratios["vs_baseline"], ratios["baseline_vs_pybullet_original"]
        lines += [
            "",
            f"Against the baseline commit `{b['commit'][:7]}` (`--baseline {b['ref']}`), in the same rounds: state "
            f"**{vs['no_render']:.2f}x** as fast (it ran {bp['no_render']:.2f}x the PyBullet loop), rgbd "
            f"**{vs['render']:.2f}x** (it ran {bp['render']:.2f}x).",
        ]
    lines += ["", "Where an action's time goes, ms per action (the mean over rounds):", "", split_table(r), ""]
    if plot_path:
        lines += [f"![simulator speed]({linked_path(plot_path)})", ""]
    lines.append(
        "Why a step costs what it does, and what each optimisation gained: "
        "[How fast is a step on 2 cores](../docs/notes/sim-speed.md)."
    )
    return "\n".join(lines) + "\n\n"


def gpu_markdown(rows: list[dict]) -> str:
    lines = [
        "## GPU (physx_cuda, rgbd, auto-reset, random actions)",
        "| num_envs | steps/s | episodes finished | GPU memory (GB) |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {g['num_envs']} | {g['env_steps_per_s']:.0f} | {g['episodes_finished']} | {g['gpu_mem_used_gb']:.1f} |"
        for g in rows
    ]
    return "\n".join(lines)


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    x = np.arange(len(MODES))
    ax[0].bar(x - 0.2, [r["env_steps_per_s"][m] for m in MODES], 0.4, label="TableClearing (ManiSkill)")
    ax[0].bar(
        x + 0.2,
        [r["reference_steps_per_s"]["pybullet_original"][m] for m in MODES],
        0.4,
        label="original report's loop (PyBullet)",
    )
    ax[0].axhline(r["reference_steps_per_s"]["pickcube_rgbd_84"], color="k", ls="--", lw=1, label="PickCube-v1 rgbd 84")
    ax[0].set_xticks(x, MODES)
    ax[0].set_ylabel("actions / s (one process)")
    ax[0].set_yscale("log")
    ax[0].legend(fontsize=7)
    names = [name for name, *_ in SCALING]
    for i, mode in enumerate(("rgbd", "state")):
        c = r["cpu_scaling"][mode]
        ax[1].bar(np.arange(len(names)) + 0.4 * i - 0.2, [c[n]["env_steps_per_s"] for n in names], 0.4, label=mode)
    ax[1].set_xticks(np.arange(len(names)), names, fontsize=8)
    ax[1].legend(fontsize=7)
    ax[1].set_xlabel("CPU vector env (SCALING in sim_speed.py)")
    ax[1].set_ylabel("env steps / s")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    entry("benchmarks.sim_speed", Args, main, check)
