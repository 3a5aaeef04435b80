"""What a run reports: TensorBoard always (W&B and Comet when asked) under the same metric names, a tqdm bar over
the budget, and the ``summary.json`` + one printed JSON line a run ends with; and :func:`read_scalars`,
which reads a run's TensorBoard logs back whole, across its resumes. See docs/training.md."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from agents.common.args import RunArgs


class Logger:
    """TensorBoard always; W&B and Comet only when asked (imported lazily). Both honour their own offline switches,
    for machines without an account or a network: ``WANDB_MODE=offline`` (the run goes to RUN_DIR/wandb/, ``wandb
    sync`` uploads it) and ``COMET_START_ONLINE=false`` (an archive in RUN_DIR/comet/, or COMET_OFFLINE_DIRECTORY;
    ``comet upload`` sends it). Comet is started with ``comet_ml.start``, which reads that switch: the
    ``comet_ml.Experiment`` used before is online only and needs an API key.

    ``clock``: the run's budget clock in seconds (``agents.common.run.Clock``, which counts the time trained before a
    ``--resume``); each logged step then carries it as ``charts/clock_min``, so a curve against minutes of training
    reads the budget's minutes, whatever gaps lie between the sessions of a resumed run."""

    CLOCK_TAG = "charts/clock_min"

    def __init__(self, run_dir: Path, args, clock: Optional[Callable[[], float]] = None):
        self.clock = clock
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir))
        self.tb.add_text("args", json.dumps(json.loads(json.dumps(asdict(args), default=str)), indent=1))
        self.wandb = self.comet = None
        config = json.loads(json.dumps(asdict(args), default=str))
        if args.wandb:
            import wandb

            self.wandb = wandb.init(project=args.wandb_project, name=run_dir.name, config=config, dir=str(run_dir))
        if args.comet:
            import comet_ml

            offline_dir = os.environ.get("COMET_OFFLINE_DIRECTORY", str(run_dir / "comet"))
            self.comet = comet_ml.start(
                project_name=args.comet_project,
                # auto_metric_logging off: Comet's hook on TensorBoard would log every scalar a second time
                experiment_config=comet_ml.ExperimentConfig(
                    name=run_dir.name, offline_directory=offline_dir, auto_metric_logging=False
                ),
            )
            self.comet.log_parameters(config)

    def scalars(self, values: dict[str, float], step: int) -> None:
        if self.clock is not None:
            values = {self.CLOCK_TAG: self.clock() / 60, **values}  # first: read before the values it dates
        for k, v in values.items():
            self.tb.add_scalar(k, v, step)
        if self.wandb is not None:
            self.wandb.log(values, step=step)
        if self.comet is not None:
            self.comet.log_metrics(values, step=step)

    def close(self) -> None:
        self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()
        if self.comet is not None:
            self.comet.end()


def budget_bar(args: RunArgs, budget: float, spent: float, desc: str, unit: str = "s"):
    """A tqdm bar over the budget, seconds or env steps (None with --no-progress)."""
    if not args.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=int(budget), initial=int(spent), unit=unit, desc=desc, dynamic_ncols=True)


@contextlib.contextmanager
def phase_bar(args: RunArgs, total: int, desc: str, unit: str):
    """A tqdm bar over one phase before training proper (expert demos, pretraining), closed when it ends; None with
    --no-progress."""
    bar = None
    if args.progress and total > 0:
        from tqdm import tqdm

        bar = tqdm(total=int(total), unit=unit, desc=desc, dynamic_ncols=True)
    try:
        yield bar
    finally:
        if bar is not None:
            bar.close()


def finish(result: dict, run_dir: Path) -> dict:
    """The run's ``summary.json`` and its last printed line (one JSON object)."""
    (run_dir / "summary.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result


def event_files(run_dir: Path) -> list[Path]:
    """A run's TensorBoard files, oldest first: by the creation second in each name, which a copy keeps, then by
    modification time."""

    def opened(f: Path) -> tuple[int, float]:
        stamp = f.name.split(".")[3]
        return (int(stamp) if stamp.isdigit() else 0, f.stat().st_mtime)

    return sorted(Path(run_dir).glob("events.out.tfevents.*"), key=opened)


def read_scalars(run_dir: Path) -> dict[str, list[tuple[int, float, float]]]:
    """Every scalar a run logged, as (step, minutes of training, value) sorted by step, over all its TensorBoard files
    (a ``--resume`` opens one more in the same folder).

    A resumed run goes back to its last checkpoint, so what the stopped process logged from the resumed run's first
    step on is dropped, as TensorBoard's own purge on restart does. The minutes are the trainer's budget clock
    (``Logger``'s ``clock``) where it logged one: each event is placed after the last clock reading before it. A file
    without one counts from when it was opened, continuing where the file before it ended."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    segments = []
    for events in event_files(run_dir):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        logged = {tag: acc.Scalars(tag) for tag in acc.Tags()["scalars"]}
        first = min((e.step for evs in logged.values() for e in evs), default=None)
        segments.append((acc.FirstEventTimestamp(), logged, first))
    out: dict[str, list[tuple[int, float, float]]] = {}
    offset = 0.0  # minutes reached by the files before this one
    for i, (opened, logged, _) in enumerate(segments):
        later = [first for _, _, first in segments[i + 1 :] if first is not None]
        cut = min(later, default=None)  # the steps from here on were trained again after a resume
        clock = sorted((e.wall_time, e.value) for e in logged.get(Logger.CLOCK_TAG, []))
        readings = np.array(clock or [(opened, offset)], dtype=float)
        for tag, evs in logged.items():
            evs = [e for e in evs if cut is None or e.step < cut]
            at = on_clock(readings, np.array([e.wall_time for e in evs], dtype=float))
            kept = [(e.step, float(m), e.value) for e, m in zip(evs, at)]
            out.setdefault(tag, []).extend(kept)
            if kept:
                offset = max(offset, max(m for _, m, _ in kept))
    return {tag: sorted(points, key=lambda p: p[0]) for tag, points in out.items()}


def on_clock(readings: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Minutes of training at the times ``walls``: for each, the last of ``readings`` (rows of time, minutes; sorted
    by time) taken at or before it (else the first), plus the seconds since."""
    k = np.maximum(np.searchsorted(readings[:, 0], walls, side="right") - 1, 0)
    return readings[k, 1] + (walls - readings[k, 0]) / 60
