"""The flags every trainer shares (``RunArgs``): the task, the seed, the wall-clock budget, the held-out
evaluation, the device and env backend, where runs go, resuming and evaluating a checkpoint, and the loggers.

``--backend``: ``gpu`` is ManiSkill's GPU-batched physx_cuda env (``--num-envs`` in one process); ``cpu`` is
``--num-envs`` worker processes (1: one env in this process); ``auto`` picks gpu when CUDA is available.
``--resume`` continues a run: networks, optimisers, data, counters and RNG, the budget counting the time
already spent. Each trainer's ``Args`` extends RunArgs and only overrides a default where its recipe needs
another one."""

from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional


@dataclass
class RunArgs:
    env_id: str = "TableClearing-IRB120-v1"
    """the task (a registered ManiSkill env id)"""
    seed: int = 1
    """seeds torch/numpy and the training episodes (always below the held-out evaluation seeds)"""
    budget_min: Optional[float] = None
    """wall-clock minutes of training (the final evaluation is extra)"""
    eval_episodes: int = 100
    """final evaluation episodes on held-out seeds (agents.common.EVAL_SEED onwards)"""
    device: str = "auto"
    """torch device of the learner (auto: CUDA when available)"""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """the envs: gpu (one GPU-batched env), cpu (worker processes) or auto (gpu when CUDA is available)"""
    exp_name: Optional[str] = None
    """run folder under --runs-dir (default: algorithm__env__obs__seed__time)"""
    runs_dir: Path = Path("runs")
    """TensorBoard logs, checkpoints and summary.json go to runs_dir/exp_name"""
    resume: Optional[Path] = None
    """continue a run from this checkpoint (networks, optimisers, data, counters, RNG)"""
    evaluate: bool = False
    """only evaluate --checkpoint on held-out episodes (videos + summary.json)"""
    checkpoint: Optional[Path] = None
    """the checkpoint --evaluate reads"""
    capture_video: bool = True
    """--evaluate: record an mp4 per episode"""
    progress: bool = True
    """a tqdm progress bar"""
    wandb: bool = False
    """also log to Weights & Biases (imported only when set; WANDB_MODE=offline: to RUN_DIR/wandb, no account)"""
    comet: bool = False
    """also log to Comet, as the original report did (imported only when set; COMET_START_ONLINE=false: an
    archive in RUN_DIR/comet, no account)"""
    wandb_project: str = "maniskill_irb120"
    """the W&B project"""
    comet_project: str = "maniskill_irb120"
    """the Comet project"""
    env_kwargs: dict = field(default_factory=dict)
    """extra gym.make keyword arguments, e.g. domain randomisation ranges; a value that reads as a Python
    literal is one (``reconfiguration_freq 5`` an int), any other stays a string"""

    def __post_init__(self) -> None:
        # the command line hands every value over as a string; ManiSkill's counters need numbers
        self.env_kwargs = {k: _literal(v) for k, v in self.env_kwargs.items()}


def _literal(value):
    if not isinstance(value, str):
        return value
    try:
        return ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return value
