"""RLlib checkpoints as agents.rllib writes and reads them: atomic ``latest`` folders that also say what they
were trained on, the trained RLModule without Ray, and its deterministic policy for held-out evaluation."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

META = "agents_rllib_args.json"


def save_checkpoint(algo, ckpt_dir: Path, args) -> Path:
    """RLlib's checkpoint plus what it was trained on (for --evaluate) into a fresh folder, then renamed over
    ``latest``: a crash mid-save never leaves a half-written ``latest``."""
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    tmp, latest, old = ckpt_dir / "latest.tmp", ckpt_dir / "latest", ckpt_dir / "latest.old"
    shutil.rmtree(tmp, ignore_errors=True)
    algo.save_to_path(str(tmp.resolve()))
    meta = dict(algo=args.algo, env_id=args.env_id, obs=args.obs, env_kwargs=args.env_kwargs, seed=args.seed)
    (tmp / META).write_text(json.dumps(meta, indent=2))
    if latest.exists():
        shutil.rmtree(old, ignore_errors=True)
        latest.rename(old)
    tmp.rename(latest)
    shutil.rmtree(old, ignore_errors=True)
    return latest


def load_module(path: Path):
    """The trained RLModule from a checkpoint folder (no env runners, no Ray needed)."""
    from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_LEARNER_GROUP, COMPONENT_RL_MODULE, DEFAULT_MODULE_ID
    from ray.rllib.core.rl_module.rl_module import RLModule

    path = Path(path).resolve()  # RLlib reads checkpoints through pyarrow, which takes only absolute paths
    sub = path / COMPONENT_LEARNER_GROUP / COMPONENT_LEARNER / COMPONENT_RL_MODULE / DEFAULT_MODULE_ID
    if not sub.is_dir():
        raise FileNotFoundError(f"{path} is not an agents.rllib checkpoint folder (no {sub.relative_to(path)})")
    return RLModule.from_checkpoint(sub)


def module_policy(module, obs_mode: str):
    """Batched obs dict -> deterministic action in [-1, 1] (the mean, squashed as the algorithm squashes)."""
    from ray.rllib.core.columns import Columns

    dist_cls = module.get_inference_action_dist_cls()

    def act(obs: dict[str, torch.Tensor]) -> torch.Tensor:
        x = obs["state"].float() if obs_mode == "state" else obs
        out = module.forward_inference({Columns.OBS: x})
        action = dist_cls.from_logits(out[Columns.ACTION_DIST_INPUTS]).to_deterministic().sample()
        return action.clamp(-1.0, 1.0)

    return act


def checkpoint_args(path: Path, args, must_match: tuple[str, ...]) -> dict:
    """What a checkpoint folder was trained on; a clear error for another folder or other ``must_match`` flags."""
    meta = Path(path) / META
    if not meta.is_file():
        raise FileNotFoundError(f"{path} is not an agents.rllib checkpoint folder (no {meta.name})")
    saved = json.loads(meta.read_text())
    for name in must_match:
        if saved[name] != getattr(args, name):
            raise ValueError(f"checkpoint {path} was trained with --{name.replace('_', '-')} {saved[name]}")
    return saved
