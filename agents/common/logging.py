"""What a run reports: TensorBoard always (W&B and Comet when asked) under the same metric names, a tqdm bar over
the wall-clock budget, and the ``summary.json`` + one printed JSON line a run ends with."""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from agents.common.args import RunArgs


class Logger:
    """TensorBoard always; W&B and Comet only when asked (imported lazily). Both honour their own offline switches,
    for machines without an account or a network: ``WANDB_MODE=offline`` (the run goes to RUN_DIR/wandb/, ``wandb
    sync`` uploads it) and ``COMET_START_ONLINE=false`` (an archive in RUN_DIR/comet/, or COMET_OFFLINE_DIRECTORY;
    ``comet upload`` sends it). Comet is started with ``comet_ml.start``, which reads that switch: the
    ``comet_ml.Experiment`` used before is online only and needs an API key."""

    def __init__(self, run_dir: Path, args):
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


def budget_bar(args: RunArgs, budget_s: float, spent_s: float, desc: str):
    """A tqdm bar over the wall-clock budget (None with --no-progress)."""
    if not args.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=int(budget_s), initial=int(spent_s), unit="s", desc=desc, dynamic_ncols=True)


def finish(result: dict, run_dir: Path) -> dict:
    """The run's ``summary.json`` and its last printed line (one JSON object)."""
    (run_dir / "summary.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result))
    return result
