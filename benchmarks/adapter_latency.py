"""Round trip per action through the controller emulator running our RAPID module: TCP loopback, a bare pty,
and a pty paced at 9600 and 115200 baud by the emulator (a pty has no line speed of its own: the emulator
holds every byte for 10 bit times, each way), beside the wire time computed from the frame sizes, under the
emulator's per-statement cost model (``--statement-cost-us``; the RAPID statements each exchange executes are
counted, and the controller time they cost is reported beside the measured round trip). Prints a table, writes
JSON; ``--update-results`` rewrites its section of benchmarks/RESULTS.md from that JSON, and ``--render-only``
rewrites it from the committed JSON without measuring (the page shows what the JSON says, nothing kept by hand).

    .venv/bin/python -m benchmarks.adapter_latency --steps 200 --json benchmarks/results/adapter_latency.json
    .venv/bin/python -m benchmarks.adapter_latency --steps 200 --update-results   # writes results/adapter_latency.json
    .venv/bin/python -m benchmarks.adapter_latency --render-only
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

from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.report import RESULTS, argv_command, raw_link, recorded_command, replace_section
from maniskill_irb120.abb.client import ABBRobot
from maniskill_irb120.abb.emulator.controller import STATEMENT_COST_US, ControllerEmulator
from maniskill_irb120.abb.protocol import OVERHEAD, GetState, ToolStep, command_frame

ROOT = Path(__file__).resolve().parents[1]

REPLY_BYTES = OVERHEAD + 26
HEAD = "## ABB adapter round trip — `benchmarks/adapter_latency.py`"
RESULTS_JSON = ROOT / "benchmarks" / "results" / "adapter_latency.json"


@dataclass
class Args:
    steps: int = 200
    """timed tool steps per channel (small steps back and forth, inside the envelope)"""
    statement_cost_us: float = STATEMENT_COST_US
    """controller time per executed RAPID statement (the emulator's estimate by default; 0: off)"""
    json: Optional[Path] = None
    """where the JSON goes (none by default; --update-results and --render-only: results/adapter_latency.json)"""
    update_results: bool = False
    """after the run, rewrite this benchmark's section of benchmarks/RESULTS.md from its JSON"""
    render_only: bool = False
    """measure nothing: rewrite the section of benchmarks/RESULTS.md from the JSON at --json"""


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


def channel_label(channel: str) -> str:
    """A JSON channel name as the table says it (``serial`` is the emulator's pty)."""
    if channel == "tcp":
        return "TCP loopback (emulator)"
    if channel == "serial":
        return "pty, no line speed (emulator)"
    return channel.replace("serial @ ", "pty paced at ") + " (emulator)"


def markdown(report: dict) -> str:
    """The round-trip table, a row per channel."""
    lines = [
        f"| channel | RAPID statements / step | their cost at {report['statement_cost_us']:g} µs (ms) "
        "| mean (ms) | p50 | p95 | max |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in report["round_trip"]:
        cells = " | ".join(f"{r[k]:.2f}" for k in ("mean_ms", "p50_ms", "p95_ms", "max_ms"))
        lines.append(
            f"| {channel_label(r['channel'])} | {r['statements_per_step']:.0f} | {r['statement_ms_per_step']:.2f} "
            f"| {cells} |"
        )
    return "\n".join(lines)


def wire_line(report: dict) -> str:
    wire = ", ".join(f"{ms:.1f} ms at {baud} baud" for baud, ms in report["wire_ms_per_step"].items())
    return (
        f"Wire time of a tool step and its reply ({report['step_frame_bytes']} + {report['reply_bytes']} bytes, "
        f"10 bits a byte): {wire}, against the loop's 50 ms period."
    )


def section(report: dict, json_path: Path) -> str:
    """This benchmark's section of RESULTS.md, from its JSON alone."""
    steps = f", {report['steps']} tool steps per channel" if "steps" in report else ""
    return (
        f"{HEAD}\n\nCommand: `{recorded_command(report['command'])}` ({report['date']}, {report['machine']}). "
        "One `ABBRobot.move_tool` round trip (the tool-step frame out, the reply back) through the controller "
        f"emulator running `assets/rapid/IRB120Server.mod`{steps}. The emulator charges every executed RAPID "
        f"statement {report['statement_cost_us']:g} µs (`STATEMENT_COST_US`, an estimate: no IRC5 has been "
        "measured), paces the program to it and counts the statements; a pty has no line speed of its own, so the "
        "paced rows hold every byte for 10 bit times each way. Raw data: "
        f"{raw_link(json_path)}.\n\n{markdown(report)}\n\n{wire_line(report)}\n\n"
    )


def update_results(json_path: Path, results: Path = RESULTS) -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path``."""
    replace_section(results, HEAD, section(json.loads(json_path.read_text()), json_path))


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before the emulator starts (``benchmarks.lib.cli`` makes it
    one line and exit status 2): --render-only with a JSON that is not there, --steps below 1, a negative
    --statement-cost-us."""
    if args.render_only:
        rendered_from(args.json or RESULTS_JSON, "--json")
        return
    if args.steps < 1:
        raise ValueError(f"--steps {args.steps}: time at least one tool step")
    if args.statement_cost_us < 0:
        raise ValueError(f"--statement-cost-us {args.statement_cost_us:g}: give 0 (off) or more")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        update_results(args.json or RESULTS_JSON)
        return json.loads((args.json or RESULTS_JSON).read_text())
    if args.update_results:
        args.json = args.json or RESULTS_JSON
    step_bytes = len(command_frame(ToolStep(0, 0, 0, 0), 1).encode())
    wire = {b: 1000 * (step_bytes + REPLY_BYTES) * 10 / b for b in (9600, 19200, 115200)}
    rows = [measure("tcp", args.steps, args.statement_cost_us), measure("serial", args.steps, args.statement_cost_us)]
    rows += [measure("serial", args.steps, args.statement_cost_us, baud) for baud in (115200, 9600)]
    out = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=argv_command("benchmarks.adapter_latency", sys.argv[1:]),
        machine=platform.platform(),
        steps=args.steps,
        step_frame_bytes=step_bytes,
        state_frame_bytes=len(command_frame(GetState(), 1).encode()),
        reply_bytes=REPLY_BYTES,
        wire_ms_per_step=wire,
        statement_cost_us=args.statement_cost_us,
        round_trip=rows,
    )
    print(markdown(out))
    print(wire_line(out))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    if args.update_results:
        update_results(args.json)
    return out


if __name__ == "__main__":
    entry("benchmarks.adapter_latency", Args, main, check)
