"""The GPU acceptance report of a source checkout: ``maniskill-irb120 doctor --gpu``'s checks plus the runs that
only a checkout can make, the trainers' tiny ``--backend gpu`` runs and the benchmark's GPU sweep, in one report
(the JSON ``benchmarks/results/gpu_acceptance.json`` holds).

The trainers (``agents/``) and the benchmarks ship with the repository, not with the package, so the package's
doctor does not start them; this script does, as a user would (``python -m agents.ppo --backend gpu ...``), and
hands them to the doctor's report as its ``programs``. Each runs in its own process, so a GPU-side crash is its
FAIL and not the end of the report. The flags a run shares with a recipe come from ``agents/recipes.py``.

The results page's GPU section is this script's: rendered from that JSON and from the GPU machine's learner-speed
JSONs (``benchmarks/learner_speed.py --device cuda`` and ``--device cpu`` on the same machine), never typed, so
the page says what the JSON says, a failed check included. ``--render-only`` needs no GPU: a page is re-rendered
wherever the JSON is, and the GPU machines are lent for minutes.

    python -m benchmarks.gpu_acceptance --jobs 8 --json-path benchmarks/results/gpu_acceptance.json
    python -m benchmarks.gpu_acceptance --jobs 8 --update-results   # also rewrites its section of RESULTS.md
    python -m benchmarks.gpu_acceptance --render-only                # the section again, from the committed JSON
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

from agents.recipes import RECIPES, STATE_PPO_NET, render
from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.report import RESULTS, argv_command, raw_link, recorded_command, replace_section
from maniskill_irb120.diagnostics.acceptance_runs import PHYSX_GPU

REPO = Path(__file__).resolve().parents[1]

HEAD = "## GPU — `benchmarks/gpu_acceptance.py`"
RESULTS_JSON = REPO / "benchmarks" / "results" / "gpu_acceptance.json"
LEARNER_JSONS = (
    REPO / "benchmarks" / "results" / "learner_speed_h200_cuda.json",
    REPO / "benchmarks" / "results" / "learner_speed_h200_host_cpu.json",
)
"""the learner-speed runs the section shows: ``learner_speed.py --device cuda`` and ``--device cpu`` on the GPU
machine, one after the other (its CPU section holds CPU figures only)"""
REASON_CHARS = 400
"""a check's reason longer than this is cut in the table (the JSON keeps it whole)"""
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
        args = ["--num-steps", str(steps), "--total-env-steps", str(2 * steps * num_envs), "--num-minibatches", "2"]
        args += ["--eval-freq", "0", "--eval-freq-episodes", "1", "--save-freq", "1", "--eval-episodes", "0"]
        if obs == "state":  # the RL-from-the-reward network (recipes.py): its normaliser on the GPU's tensors
            args += render(STATE_PPO_NET)
    elif name == "sac":
        args = ["--budget-min", "0.05", "--demo-episodes", "1", "--bc-pretrain-updates", "5"]
        args += ["--critic-warmup-updates", "5", "--batch-size", "16", "--log-freq", "20", "--save-freq", "40"]
        args += ["--eval-episodes", "1", "--no-capture-video"]
    else:
        # the camera recipe (dagger-rgbd-bf16; --precision auto: bf16 on a CPU that has it) at toy sizes: its flags,
        # then this run's over them (round 0 as many updates as the other rounds)
        args = [*RECIPES[CAMERA_RECIPE].argv(), "--initial-updates", "0"] if obs == "rgbd" else []
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
    cmd = [sys.executable, "-m", "benchmarks.sim_speed", "--gpu-only", "--gpu-num-envs", *map(str, BENCH_ENVS)]
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


# --------------------------------------------------------------------------- the results page's GPU section
def one_line(reason: str, limit: int = REASON_CHARS) -> str:
    """A check's reason for a table cell: its first line, a long parenthesis (an exception's repr, a URL's
    retries) cut to its first word, so that what the reason tells the reader to do survives; at most ``limit``
    characters."""
    text = (reason.strip().splitlines() or [""])[0]
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch == "(":
            if depth == 0:
                start = i
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
            if depth == 0:
                inner = text[start + 1 : i]
                word = (inner.split(":")[0].split() or [""])[0]
                out.append(f"({word} …)" if len(inner) > 60 else f"({inner})")
        elif depth == 0:
            out.append(ch)
    if depth:  # unbalanced: keep the rest as it was
        out.append(text[start:])
    short = "".join(out)
    short = short if len(short) <= limit else short[: limit - 1].rstrip() + "…"
    return short.replace("|", "\\|")


def machine_line(report: dict) -> str:
    """The device, driver, CUDA, versions, commit and date the report ran with, from its ``environment``."""
    env = report["environment"]
    mem = f" ({env['device_memory_gib']} GiB)" if env.get("device_memory_gib") else ""
    versions = ", ".join(f"{k[8:]} {v or 'not installed'}" for k, v in env.items() if k.startswith("version_"))
    commit = f"commit `{env['commit']}`" if env.get("commit") else "commit not recorded"
    return (
        f"Machine: {env.get('device') or 'no CUDA device'}{mem}, driver {env.get('driver') or 'unknown'}, CUDA "
        f"{env.get('cuda_runtime') or 'none'} (torch's build); Python {env['python']}, {versions}; {commit}; "
        f"{report['date']}."
    )


def checks_table(checks: list[dict]) -> str:
    lines = ["| check | result | reason |", "|---|---|---|"]
    for c in checks:
        result = {True: "ok", False: "**FAILED**", None: "skipped"}[c["ok"]]
        lines.append(f"| {c['name']} | {result} | {one_line(c['reason'])} |")
    return "\n".join(lines)


def throughput_text(rows: list[dict]) -> str:
    """The state-obs steps/s table; one sentence where no batch size was timed."""
    if not rows:
        return ""
    if all("error" in r for r in rows):
        errors = sorted({r["error"] for r in rows})
        sizes = ", ".join(str(r["num_envs"]) for r in rows)
        return f"No steps/s were timed: at {sizes} envs, {'; '.join(errors)}.\n\n"
    lines = [
        "State-obs steps/s (TableClearing-IRB120-v1, random actions, auto-reset):",
        "",
        "| num_envs | env steps/s | GPU memory (GB) |",
        "|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['num_envs']} | {one_line(r['error'])} | |")
        else:
            mem = f"{r['gpu_mem_used_gb']:.1f}" if r.get("gpu_mem_used_gb") else ""
            lines.append(f"| {r['num_envs']} | {r['env_steps_per_s']:.0f} | {mem} |")
    return "\n".join(lines) + "\n\n"


def verdict(report: dict) -> str:
    """What the checks add up to; that ``physx_cuda`` did not start is the PhysX-library check's FAIL, not prose."""
    checks = report["checks"]
    skipped = sum(c["ok"] is None for c in checks)
    physx = next((c for c in checks if c["name"] == PHYSX_GPU), None)
    if physx is not None and physx["ok"] is False:
        others = len(checks) - 1
        which = f"the other {others} checks" if skipped == others else f"{skipped} of the {others} other checks"
        return f"`physx_cuda` did not start there: `{PHYSX_GPU}` failed, so {which}, which need it, were skipped."
    failed = [c["name"] for c in checks if c["ok"] is False]
    if failed:
        return f"{len(failed)} of {len(checks)} checks failed ({', '.join(failed)}); {skipped} skipped."
    return f"Every check that ran passed ({len(checks) - skipped} of {len(checks)}; {skipped} skipped)."


def command_text(report: dict, json_path: Path) -> str:
    """The command that wrote the report; a report written before reports recorded it gets the command that
    writes one like it now, from its own ``jobs`` and ``trainer_envs``, said as such."""
    if report.get("command"):
        return f"Command: `{recorded_command(report['command'])}`."
    argv = ["--jobs", str(report.get("jobs", 1))]
    if report.get("trainer_envs") not in (None, Args.trainer_envs):
        argv += ["--trainer-envs", str(report["trainer_envs"])]
    path = Path(json_path).resolve()
    shown = path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else path.as_posix()
    command = argv_command("benchmarks.gpu_acceptance", [*argv, "--json-path", shown])
    return f"The JSON records no command; `{command}` writes a report like it now."


def learner_table(gpu: dict, cpu: dict, gpu_path: Path, cpu_path: Path) -> str:
    """One camera-learner update on the GPU against the same machine's CPU, configuration by configuration."""
    if gpu.get("device", "cpu") == "cpu" or cpu.get("device", "cpu") != "cpu":
        raise ValueError(f"expected a CUDA run and a CPU run; got {gpu.get('device')!r} and {cpu.get('device')!r}")
    if gpu["machine"] != cpu["machine"]:
        raise ValueError(f"the two runs are from different machines: {gpu['machine']!r} and {cpu['machine']!r}")
    on_cpu = {r["config"]: r for r in cpu["rows"]}
    rounds = "/".join(map(str, sorted({len(r["rounds_ms"]) for r in [*gpu["rows"], *cpu["rows"]]})))
    lines = [
        f"| configuration | {gpu['device']} (ms per update, median of {rounds} rounds) | its CPUs (ms) "
        "| speed-up on the GPU |",
        "|---|---|---|---|",
    ]
    for r in gpu["rows"]:
        c = on_cpu.get(r["config"])
        cells = f"{c['ms']:.1f} | {c['ms'] / r['ms']:.1f}x" if c else "not run | "
        lines.append(f"| {r['config']} | {r['ms']:.1f} | {cells} |")
    note = f"; {gpu['note']}" if gpu.get("note") else ""
    return (
        f'One update of the camera DAgger recipe (`agents.dagger.train_round`, as in "Camera learner update") on '
        f"the {gpu['device']} and on the same machine's CPUs ({gpu['machine']}; torch {gpu['versions']['torch']}"
        f"{note}). Commands: `{recorded_command(gpu['command'])}` ({gpu['date']}), then "
        f"`{recorded_command(cpu['command'])}` ({cpu['date']}). Raw data: {raw_link(gpu_path)}, "
        f"{raw_link(cpu_path)}.\n\n" + "\n".join(lines) + "\n\n"
    )


def section(report: dict, json_path: Path, learner: list[tuple[Path, Path]] | tuple = ()) -> str:
    """The results page's GPU section, from the acceptance report (at ``json_path``, which it links) and the
    learner-speed JSON pairs in ``learner`` ((CUDA run, same machine's CPU run) each) alone."""
    parts = [
        f"{HEAD}\n\n{machine_line(report)} {command_text(report, json_path)} Raw data: {raw_link(json_path)}.\n\n",
        f"The acceptance checks ({report['sim_backend']}, num_envs={report['num_envs']}"
        + (f", trainers num_envs={report['trainer_envs']}" if report.get("trainer_envs") is not None else "")
        + f"): {verdict(report)}\n\n{checks_table(report['checks'])}\n\n",
        throughput_text(report.get("throughput") or []),
    ]
    for gpu_path, cpu_path in learner:
        gpu, cpu = (json.loads(Path(p).read_text()) for p in (gpu_path, cpu_path))
        parts.append(learner_table(gpu, cpu, gpu_path, cpu_path))
    parts.append("What else ran there, and why: [What ran on a lent H200](../docs/notes/gpu-h200.md).\n\n")
    return "".join(parts)


def update_results(json_path: Path, results: Path = RESULTS, learner: tuple = (LEARNER_JSONS,)) -> None:
    """Rewrite the GPU section of ``results`` from the report at ``json_path`` and the learner-speed pairs."""
    replace_section(results, HEAD, section(json.loads(Path(json_path).read_text()), json_path, list(learner)))


def record_command(json_path: Path, command: str) -> None:
    """Put the command into the report the doctor wrote, first, so that the page shows how it was made."""
    report = json.loads(json_path.read_text())
    json_path.write_text(json.dumps({"command": command, **report}, indent=2))


@dataclass
class Args:
    json: bool = False
    """print the report as JSON (default: plain text)"""
    json_path: Optional[Path] = None
    """also write the report there (benchmarks/results/gpu_acceptance.json is the committed one; --update-results
    and --render-only: that one by default)"""
    jobs: int = 1
    """checks side by side, each in its own process (the obs-mode sweep split per task and mode)"""
    trainer_envs: int = 64
    """num_envs of the trainers' tiny runs (the camera recipe's at most 8)"""
    update_results: bool = False
    """after the run, rewrite the GPU section of benchmarks/RESULTS.md from the report's JSON"""
    render_only: bool = False
    """run nothing (no GPU needed): rewrite the GPU section of benchmarks/RESULTS.md from the JSON at --json-path"""


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any check runs (``benchmarks.lib.cli`` makes it one
    line and exit status 2): --jobs or --trainer-envs below 1, --render-only with a JSON that is not there."""
    if args.render_only:
        rendered_from(args.json_path or RESULTS_JSON, "--json-path")
        return
    if args.jobs < 1:
        raise ValueError(f"--jobs {args.jobs}: expected 1 or more")
    if args.trainer_envs < 1:
        raise ValueError(f"--trainer-envs {args.trainer_envs}: expected 1 or more")


def main(args: Args) -> int:
    """0 when every check passes, 1 when one fails, 2 without a CUDA device (as ``doctor --gpu``); --render-only
    0 once the section is written."""
    check(args)
    if args.render_only:
        update_results(args.json_path or RESULTS_JSON)
        return 0
    from maniskill_irb120.diagnostics.doctor import gpu_main

    if args.update_results:
        args.json_path = args.json_path or RESULTS_JSON
    rc = gpu_main(
        json_output=args.json,
        json_path=None if args.json_path is None else str(args.json_path),
        jobs=args.jobs,
        programs=PROGRAMS,
        trainer_envs=args.trainer_envs,
        commit=git_commit(),
    )
    if args.json_path is not None and rc in (0, 1):  # 2: no CUDA, nothing ran and nothing was written
        record_command(args.json_path, argv_command("benchmarks.gpu_acceptance", sys.argv[1:]))
        if args.update_results:
            update_results(args.json_path)
    return rc


if __name__ == "__main__":
    entry("benchmarks.gpu_acceptance", Args, main, check, exit_status=True)
