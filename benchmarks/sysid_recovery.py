"""System identification on the emulator: inject command latency and speed scale, log ``sysid.excite``'s
tool steps, fit, and compare with the emulator run without injection (its own latency is its Python RAPID
interpreter's). Prints a table, writes JSON; ``--update-results`` rewrites its section of benchmarks/RESULTS.md
from that JSON, and ``--render-only`` rewrites it from the committed JSON without measuring.

    .venv/bin/python -m benchmarks.sysid_recovery --json benchmarks/results/sysid_recovery.json
    .venv/bin/python -m benchmarks.sysid_recovery --update-results   # writes results/sysid_recovery.json
    .venv/bin/python -m benchmarks.sysid_recovery --render-only
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.report import RESULTS, argv_command, raw_link, recorded_command, replace_section
from maniskill_irb120.abb.emulator.controller import ControllerEmulator
from maniskill_irb120.sim2real.agent import IRB120RealAgent
from maniskill_irb120.sim2real.sysid import excite, fit, load_log, log_arrays

ROOT = Path(__file__).resolve().parents[1]

HEAD = "## System identification on the emulator — `benchmarks/sysid_recovery.py`"
RESULTS_JSON = ROOT / "benchmarks" / "results" / "sysid_recovery.json"
CASES = [(0.0, 1.0), (20.0, 1.0), (40.0, 0.6), (0.0, 0.5), (30.0, 0.8)]


@dataclass
class Args:
    steps: int = 100
    """tool steps per run (20 Hz)"""
    repeats: int = 3
    """runs per case (the fit's spread)"""
    json: Optional[Path] = None
    """where the JSON goes (none by default; --update-results and --render-only: results/sysid_recovery.json)"""
    update_results: bool = False
    """after the run, rewrite this benchmark's section of benchmarks/RESULTS.md from its JSON"""
    render_only: bool = False
    """measure nothing: rewrite the section of benchmarks/RESULTS.md from the JSON at --json"""


def run(latency_ms: float, speed_scale: float, steps: int, seed: int) -> dict:
    emu = ControllerEmulator("tcp", latency_ms=latency_ms, speed_scale=speed_scale)
    agent = IRB120RealAgent(emu.start())
    agent.start()
    try:
        excite(agent, steps=steps, seed=seed)
    finally:
        agent.stop()
        emu.stop()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "real_0.npz"
        np.savez(path, **log_arrays(agent.log, 0.05))
        return fit([load_log(path)])


def summary(report: dict) -> list[dict]:
    """Each case's fits: latency less the emulator's own (ms), speed scale and RMS joint errors (mrad), mean and
    spread over its runs."""
    base = report["own_latency_s"]
    out = []
    for r in report["rows"]:
        lat = [1000 * (f["latency_s"] - base) for f in r["fits"]]
        sc = [f["speed_scale"] for f in r["fits"]]
        out.append(
            dict(
                injected_latency_ms=r["injected_latency_ms"],
                injected_speed_scale=r["injected_speed_scale"],
                latency_ms=float(np.mean(lat)),
                latency_std_ms=float(np.std(lat)),
                speed_scale=float(np.mean(sc)),
                speed_scale_std=float(np.std(sc)),
                fit_mrad=float(np.mean([1000 * f["rms_joint_error_fit_rad"] for f in r["fits"]])),
                nominal_mrad=float(np.mean([1000 * f["rms_joint_error_nominal_rad"] for f in r["fits"]])),
                runs=len(r["fits"]),
            )
        )
    return out


def markdown(report: dict) -> str:
    lines = [
        "| injected latency (ms) | fitted − emulator's own (ms) | injected speed scale | fitted "
        "| RMS joint error, fit / nominal robot (mrad) |",
        "|---|---|---|---|---|",
    ]
    for r in summary(report):
        lines.append(
            f"| {r['injected_latency_ms']:.0f} | {r['latency_ms']:.1f} ± {r['latency_std_ms']:.1f} "
            f"| {r['injected_speed_scale']:.2f} | {r['speed_scale']:.3f} ± {r['speed_scale_std']:.3f} "
            f"| {r['fit_mrad']:.2f} / {r['nominal_mrad']:.2f} |"
        )
    return "\n".join(lines)


def section(report: dict, json_path: Path) -> str:
    """This benchmark's section of RESULTS.md, from its JSON alone."""
    rows = summary(report)
    runs = sorted({r["runs"] for r in rows})
    steps = f"{report['steps']} " if "steps" in report else ""
    worst = max(abs(r["latency_ms"] - r["injected_latency_ms"]) for r in rows)
    closer = [r["nominal_mrad"] / r["fit_mrad"] for r in rows]
    return (
        f"{HEAD}\n\nCommand: `{recorded_command(report['command'])}` ({report['date']}, {report['machine']}). "
        f"`sysid.excite` drives {steps}tool steps of random size at 20 Hz through the controller emulator with a "
        f"command latency and a speed scale injected, {'/'.join(map(str, runs))} runs per case; `sysid.fit` fits "
        "latency and speed scale to the logged exchanges. The emulator has a latency of its own (its interpreted "
        f"RAPID: {1000 * report['own_latency_s']:.1f} ms here, the fit with nothing injected), so the recovered "
        f"latency is the fit less that. Raw data: {raw_link(json_path)}.\n\n{markdown(report)}\n\n"
        f"The recovered latency is within {worst:.1f} ms of the injected one in every case; the fitted model "
        f"tracks the logged joints {min(closer):.1f}–{max(closer):.1f}× closer than the nominal robot (latency 0, "
        "speed scale 1).\n\n"
    )


def update_results(json_path: Path, results: Path = RESULTS) -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path``."""
    replace_section(results, HEAD, section(json.loads(json_path.read_text()), json_path))


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before the emulator starts (``benchmarks.lib.cli`` makes it
    one line and exit status 2): --render-only with a JSON that is not there, --steps or --repeats below 1."""
    if args.render_only:
        rendered_from(args.json or RESULTS_JSON, "--json")
        return
    for flag, value in (("--steps", args.steps), ("--repeats", args.repeats)):
        if value < 1:
            raise ValueError(f"{flag} {value}: expected 1 or more")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        update_results(args.json or RESULTS_JSON)
        return json.loads((args.json or RESULTS_JSON).read_text())
    if args.update_results:
        args.json = args.json or RESULTS_JSON
    rows = []
    for latency_ms, scale in CASES:
        fits = [run(latency_ms, scale, args.steps, seed) for seed in range(args.repeats)]
        rows.append(dict(injected_latency_ms=latency_ms, injected_speed_scale=scale, fits=fits))
    base = np.mean([f["latency_s"] for f in rows[0]["fits"]])
    out = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=argv_command("benchmarks.sysid_recovery", sys.argv[1:]),
        machine=platform.platform(),
        steps=args.steps,
        repeats=args.repeats,
        own_latency_s=float(base),
        rows=rows,
    )
    print(markdown(out))
    print(f"emulator's own latency (no injection): {1000 * base:.1f} ms")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    if args.update_results:
        update_results(args.json)
    return out


if __name__ == "__main__":
    entry("benchmarks.sysid_recovery", Args, main, check)
