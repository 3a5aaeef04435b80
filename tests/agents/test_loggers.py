"""W&B and Comet, the loggers every trainer offers (``--wandb``, ``--comet``), in their offline modes: one short
DAgger run (the cheapest trainer run of tests/agents) logs to both, and each offline run holds the metrics the
trainer logged to TensorBoard."""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import pytest

wandb = pytest.importorskip("wandb")
pytest.importorskip("comet_ml")

from wandb.proto import wandb_internal_pb2  # noqa: E402

BLOCK, HEADER = 32768, struct.Struct("<IHB")  # LevelDB's log format, which W&B's .wandb files use


def wandb_records(path: Path) -> list:
    """The protobuf records of an offline ``.wandb`` file (7-byte file header ``:W&B``, then 32 KiB blocks of
    checksum / length / type-prefixed chunks; a record spans chunks FIRST, MIDDLE..., LAST)."""
    data = path.read_bytes()
    assert data[:4] == b":W&B", data[:8]
    out, pos, parts = [], 7, b""
    while pos + HEADER.size <= len(data):
        left = BLOCK - pos % BLOCK
        if left < HEADER.size:
            pos += left  # block trailer: zero padding
            continue
        _, length, kind = HEADER.unpack_from(data, pos)
        chunk = data[pos + HEADER.size : pos + HEADER.size + length]
        pos += HEADER.size + length
        if kind == 0 and length == 0:
            break
        parts += chunk
        if kind in (1, 4):  # FULL or LAST
            rec = wandb_internal_pb2.Record()
            rec.ParseFromString(parts)
            out.append(rec)
            parts = b""
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory, tiny_dagger):
    tmp = tmp_path_factory.mktemp("loggers")
    mp = pytest.MonkeyPatch()
    mp.setenv("WANDB_MODE", "offline")
    mp.setenv("WANDB_SILENT", "true")
    mp.setenv("COMET_START_ONLINE", "false")
    mp.delenv("COMET_API_KEY", raising=False)
    mp.delenv("COMET_OFFLINE_DIRECTORY", raising=False)
    try:
        res = tiny_dagger(tmp, wandb=True, comet=True)
    finally:
        mp.undo()
    return Path(res["run_dir"]), res


def test_wandb_offline_run_holds_the_logged_metrics(run):
    run_dir, res = run
    (run_file,) = run_dir.glob("wandb/offline-run-*/run-*.wandb")
    records = wandb_records(run_file)
    history = {}
    for r in records:
        if r.WhichOneof("record_type") == "history":
            for item in r.history.item:
                history.setdefault(item.key or "/".join(item.nested_key), []).append(json.loads(item.value_json))
    run_rec = next(r.run for r in records if r.WhichOneof("record_type") == "run")
    assert run_rec.display_name == "t" and run_rec.project == "maniskill_irb120"
    assert history["charts/dataset"] and all(v > 0 for v in history["charts/dataset"])
    assert history["eval/success_rate"] == [pytest.approx(res["success_rate"])]


def test_comet_offline_archive_holds_the_logged_metrics(run):
    run_dir, res = run
    (archive,) = (run_dir / "comet").glob("*.zip")
    with zipfile.ZipFile(archive) as z:
        messages = [json.loads(line) for line in z.read("messages.json").decode().splitlines()]
    metrics = {}
    for m in messages:
        if m["type"] == "metric_msg":
            metrics.setdefault(m["payload"]["metric"]["metricName"], []).append(m["payload"]["metric"]["metricValue"])
    assert metrics["charts/dataset"] and all(float(v) > 0 for v in metrics["charts/dataset"])
    assert [float(v) for v in metrics["eval/success_rate"]] == [pytest.approx(res["success_rate"])]
    params = [m for m in messages if m["type"] == "parameter_msg"]
    assert any(m["payload"]["param"]["paramName"] == "budget_min" for m in params)


def test_a_phase_before_training_shows_its_own_bar_and_closes_it(capsys):
    """SAC's expert demos and pretraining take minutes before the first RL step: each shows a bar (on stderr) that
    counts its units and is closed when the phase ends; --no-progress shows none."""
    from agents.common import RunArgs, phase_bar

    with phase_bar(RunArgs(progress=True), 3, "expert demos", "episode") as bar:
        for _ in range(3):
            bar.update(1)
    assert bar.n == 3
    err = capsys.readouterr().err
    assert "expert demos" in err and "3/3" in err
    with phase_bar(RunArgs(progress=False), 3, "expert demos", "episode") as bar:
        assert bar is None
    assert capsys.readouterr().err == ""
