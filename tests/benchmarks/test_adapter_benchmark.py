"""benchmarks/adapter_latency.py runs and writes its JSON (smoke: timings are never asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_adapter_latency_runs(tmp_path):
    out = tmp_path / "lat.json"
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.adapter_latency", "--steps", "5", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    channels = {x["channel"] for x in r["round_trip"]}
    assert channels == {"tcp", "serial", "serial @ 115200 baud", "serial @ 9600 baud"} and r["reply_bytes"] == 32
