"""System identification on the emulator: inject command latency and speed scale, log ``sysid.excite``'s
tool steps, fit, and compare with the emulator run without injection (its own latency is its Python RAPID
interpreter's). Prints a table, writes JSON.

    .venv/bin/python benchmarks/sysid_recovery.py --json benchmarks/results/sysid_recovery.json
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
import tyro

from maniskill_irb120.abb.emulator.controller import ControllerEmulator
from maniskill_irb120.sim2real.agent import IRB120RealAgent
from maniskill_irb120.sim2real.sysid import excite, fit, load_log, log_arrays

CASES = [(0.0, 1.0), (20.0, 1.0), (40.0, 0.6), (0.0, 0.5), (30.0, 0.8)]


@dataclass
class Args:
    steps: int = 100
    """tool steps per run (20 Hz)"""
    repeats: int = 3
    """runs per case (the fit's spread)"""
    json: Optional[Path] = None


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


def main(args: Args) -> dict:
    rows = []
    for latency_ms, scale in CASES:
        fits = [run(latency_ms, scale, args.steps, seed) for seed in range(args.repeats)]
        rows.append(dict(injected_latency_ms=latency_ms, injected_speed_scale=scale, fits=fits))
    base = np.mean([f["latency_s"] for f in rows[0]["fits"]])
    print(
        "| injected latency (ms) | fitted - emulator's own (ms) | injected speed scale | fitted "
        "| RMS error fit / nominal (mrad) |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        lat = [1000 * (f["latency_s"] - base) for f in r["fits"]]
        sc = [f["speed_scale"] for f in r["fits"]]
        err = [(1000 * f["rms_joint_error_fit_rad"], 1000 * f["rms_joint_error_nominal_rad"]) for f in r["fits"]]
        fit_err, nominal_err = np.mean([e[0] for e in err]), np.mean([e[1] for e in err])
        print(
            f"| {r['injected_latency_ms']:.0f} | {np.mean(lat):.1f} ± {np.std(lat):.1f} "
            f"| {r['injected_speed_scale']:.2f} | {np.mean(sc):.3f} ± {np.std(sc):.3f} "
            f"| {fit_err:.2f} / {nominal_err:.2f} |"
        )
    print(f"emulator's own latency (no injection): {1000 * base:.1f} ms")
    out = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=" ".join(sys.argv),
        machine=platform.platform(),
        own_latency_s=float(base),
        rows=rows,
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main(tyro.cli(Args))
