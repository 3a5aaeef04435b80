"""Round trip per action through the controller emulator running our RAPID module: TCP loopback, a bare pty,
and a pty paced at 9600 and 115200 baud by the emulator (a pty has no line speed of its own: the emulator
holds every byte for 10 bit times, each way), beside the wire time computed from the frame sizes, under the
emulator's per-statement cost model (``--statement-cost-us``; the RAPID statements each exchange executes are
counted, and the controller time they cost is reported beside the measured round trip). Prints a table, writes
JSON.

    .venv/bin/python benchmarks/adapter_latency.py --steps 200 --json benchmarks/results/adapter_latency.json
"""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from maniskill_irb120.abb.client import ABBRobot
from maniskill_irb120.abb.emulator.controller import STATEMENT_COST_US, ControllerEmulator
from maniskill_irb120.abb.protocol import OVERHEAD, GetState, ToolStep, command_frame

REPLY_BYTES = OVERHEAD + 26


@dataclass
class Args:
    steps: int = 200
    """timed tool steps per channel (small steps back and forth, inside the envelope)"""
    statement_cost_us: float = STATEMENT_COST_US
    """controller time per executed RAPID statement (the emulator's estimate by default; 0: off)"""
    json: Optional[Path] = None


def measure(channel: str, steps: int, cost_us: float, baud: int | None = None) -> dict:
    emu = ControllerEmulator(channel, baud=baud, statement_cost_us=cost_us)
    times = []
    with ABBRobot.connect(emu.start(), timeout=1.0) as robot:
        n0 = emu.interp.statements
        for i in range(steps):
            a = [0.2 if (i // 10) % 2 == 0 else -0.2, 0, 0, 0, 1.0]
            t0 = time.perf_counter()
            robot.move_tool(a)
            times.append(time.perf_counter() - t0)
        statements = (emu.interp.statements - n0) / steps
    emu.stop()
    t = np.asarray(times) * 1000
    return dict(
        channel=channel if baud is None else f"{channel} @ {baud} baud",
        statements_per_step=float(statements),
        statement_ms_per_step=float(statements * cost_us / 1000),
        mean_ms=float(t.mean()),
        p50_ms=float(np.median(t)),
        p95_ms=float(np.percentile(t, 95)),
        max_ms=float(t.max()),
    )


def main(args: Args) -> dict:
    step_bytes = len(command_frame(ToolStep(0, 0, 0, 0), 1).encode())
    wire = {b: 1000 * (step_bytes + REPLY_BYTES) * 10 / b for b in (9600, 19200, 115200)}
    rows = [measure("tcp", args.steps, args.statement_cost_us), measure("serial", args.steps, args.statement_cost_us)]
    rows += [measure("serial", args.steps, args.statement_cost_us, baud) for baud in (115200, 9600)]
    out = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=" ".join(sys.argv),
        machine=platform.platform(),
        step_frame_bytes=step_bytes,
        state_frame_bytes=len(command_frame(GetState(), 1).encode()),
        reply_bytes=REPLY_BYTES,
        wire_ms_per_step=wire,
        statement_cost_us=args.statement_cost_us,
        round_trip=rows,
    )
    print(
        f"| channel | RAPID statements / step | their cost at {args.statement_cost_us:g} us (ms) "
        "| mean (ms) | p50 | p95 | max |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        cells = " | ".join(f"{r[k]:.2f}" for k in ("mean_ms", "p50_ms", "p95_ms", "max_ms"))
        print(
            f"| {r['channel']} (emulator) | {r['statements_per_step']:.0f} "
            f"| {r['statement_ms_per_step']:.2f} | {cells} |"
        )
    print(
        "wire time per tool step + reply: "
        + ", ".join(f"{b} baud {ms:.1f} ms" for b, ms in wire.items())
        + " (at 9600 baud the bytes alone take 49 ms of the 50 ms period: the paced row shows what is left)"
    )
    print(f"frames: tool step {step_bytes} B, reply {REPLY_BYTES} B")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
