"""A checkpoint's self-describing policy section, and the acting function built from it.

Each trainer writes one through :func:`policy_section` next to its training state; a deployment reads it with
:func:`read_policy_section` and acts with :func:`acting`, without the trainer's code. Checkpoints written
before the section existed are read through their ``format``, ``signature`` and ``args``."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Optional

import torch
import torch.nn as nn

from maniskill_irb120.errors import MissingFile, UsageError
from maniskill_irb120.policies.nets import DeterministicActor
from maniskill_irb120.policies.ppo import Agent
from maniskill_irb120.policies.sac import SAC

MODULES: dict[str, type[nn.Module]] = {"ppo": Agent, "dagger": DeterministicActor, "sac": SAC}
"""policy kind -> the module class its ``config`` constructs"""
STOCHASTIC = {"ppo": True, "dagger": False, "sac": True}
"""whether a kind has a distribution to sample"""
LEGACY_FORMATS = {
    "maniskill_irb120.ppo/1": "ppo",
    "maniskill_irb120.dagger/1": "dagger",
    "maniskill_irb120.sac/1": "sac",
}


def policy_section(
    kind: str,
    module: nn.Module,
    config: dict,
    *,
    env_id: str,
    obs: str,
    action_frame: str,
    obs_without: tuple[str, ...] = (),
    control_mode: str = "pd_ee_delta_tool",
    reward_mode: Optional[str] = None,
    env_kwargs: Optional[dict] = None,
    eval_deterministic: bool = True,
    init_std: float = 0.0,
) -> dict:
    """What a deployment needs to act like ``module``: its kind, constructor ``config`` and weights, and the env
    it reads (task, obs layout, hidden obs keys, control mode, action frame, env kwargs) and how it was evaluated
    (``eval_deterministic``; ``init_std``: the noise a sampling SAC adds around its reference)."""
    if kind not in MODULES:
        raise ValueError(f"unknown policy kind {kind!r}; expected one of {sorted(MODULES)}")
    if not isinstance(module, MODULES[kind]):
        raise TypeError(f"a {kind!r} policy is a {MODULES[kind].__name__}, not a {type(module).__name__}")
    return dict(
        kind=kind,
        config=dict(config),
        state_dict=module.state_dict(),
        env_id=env_id,
        obs=obs,
        obs_without=list(obs_without),
        action_frame=action_frame,
        control_mode=control_mode,
        reward_mode=reward_mode,
        env_kwargs=dict(env_kwargs or {}),
        eval_deterministic=bool(eval_deterministic),
        init_std=float(init_std),
        stochastic=STOCHASTIC[kind],
    )


def legacy_section(ckpt: dict) -> dict:
    """The section of a checkpoint written before sections existed, from its format, signature and args."""
    kind = LEGACY_FORMATS[ckpt["format"]]
    args, sig = ckpt.get("args", {}), dict(ckpt["signature"])
    if kind == "sac":
        sig["init_alpha"] = 1.0  # its log_alpha comes with the weights
    section = dict(
        kind=kind,
        config=sig,
        state_dict=ckpt["model"],
        env_id=args.get("env_id", "TableClearing-IRB120-v1"),
        obs=args.get("obs", "rgbd" if kind == "ppo" else "state"),
        obs_without=list(args.get("obs_without") or ()),
        action_frame=args.get("action_frame", "tool" if kind == "ppo" else "world"),
        control_mode=args.get("control_mode", "pd_ee_delta_tool"),
        reward_mode=args.get("reward_mode", None if kind == "dagger" else "normalized_dense"),
        env_kwargs=dict(args.get("env_kwargs") or {}),
        eval_deterministic=bool(args.get("eval_deterministic", True)),
        init_std=float(args.get("init_std", 0.1 if kind == "sac" else 0.0)),
        stochastic=STOCHASTIC[kind],
    )
    return section


def section_of(ckpt: Any, where: str = "checkpoint") -> dict:
    """The policy section of a loaded checkpoint dict (its ``policy``, or one rebuilt from an older format)."""
    if isinstance(ckpt, dict) and isinstance(ckpt.get("policy"), dict):
        return ckpt["policy"]
    fmt = ckpt.get("format") if isinstance(ckpt, dict) else None
    if fmt in LEGACY_FORMATS:
        return legacy_section(ckpt)
    raise UsageError(f"{where}: format {fmt!r} is none of {sorted(LEGACY_FORMATS)} and it has no policy section")


def read_checkpoint(path: Path, where: Optional[str] = None) -> Any:
    """What torch saved at ``path`` (on the CPU), or an error that says why not (``where``: who asked for it).
    The one reader of checkpoint files, for the trainers and for deployment alike."""
    path = Path(path)
    if not path.is_file():
        raise MissingFile(f"{where + ': ' if where else ''}checkpoint {path} does not exist")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise UsageError(
            f"{where or f'checkpoint {path}'} is not a readable torch checkpoint ({e}): give a trainer's checkpoint "
            "(RUN_DIR/checkpoints/*.pt) or a file export-policy wrote"
        ) from e


def read_policy_section(path: Path, where: Optional[str] = None) -> dict:
    """The policy section of the checkpoint file at ``path``, or an error that says why not."""
    where = where or str(path)
    return section_of(read_checkpoint(path, where), where)


def section_sha256(section: dict) -> str:
    """A sha256 of the policy a section holds, its weights and every setting it acts by, and nothing of the file
    around it: a trainer's checkpoint and ``export-policy``'s copy of it hash the same, other weights do not.
    Deterministic: dict keys in sorted order, each tensor as its dtype, shape and raw bytes."""
    h = hashlib.sha256()

    def feed(x: Any) -> None:
        if torch.is_tensor(x):
            t = x.detach().cpu().contiguous()
            h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        elif isinstance(x, dict):
            h.update(f"D{len(x)}".encode())
            for k in sorted(x, key=str):
                h.update(f"K{k!r}".encode())
                feed(x[k])
        elif isinstance(x, (list, tuple)):
            h.update(f"L{len(x)}".encode())
            for v in x:
                feed(v)
        else:
            h.update(f"V{x!r}".encode())

    feed(section)
    return h.hexdigest()


def policy_module(section: dict, device="cpu") -> nn.Module:
    """The section's module with its weights, in eval mode."""
    config = dict(section["config"])
    if config.get("image_shape"):
        config["image_shape"] = tuple(config["image_shape"])
    module = MODULES[section["kind"]](**config).to(device)
    module.load_state_dict(section["state_dict"])
    return module.eval()


def acting(section: dict, sampled: bool = False, device="cpu") -> Callable[[dict], torch.Tensor]:
    """Batched obs dict -> actions: the deterministic action, or with ``sampled`` a draw from the policy's
    distribution (a SAC with a reference explores around it with the section's ``init_std``, as in training)."""
    if sampled and not section["stochastic"]:
        raise ValueError(f"a {section['kind']} policy is deterministic: it has no distribution to sample")
    module = policy_module(section, device)
    if section["kind"] == "ppo":
        return lambda obs: module.get_action(obs, deterministic=not sampled)
    if section["kind"] == "sac":
        return lambda obs: module.act(obs, deterministic=not sampled, noise=section["init_std"])
    return module


def export_policy(src: Path, dst: Path, command: str) -> dict:
    """Write ``src``'s policy section alone to ``dst``: what ``sim2real-eval --policy`` and the benchmarks read,
    without the trainer's optimiser and replay state (a committable file), with the ``command`` that trained it.
    Returns what was written, less the weights."""
    section = read_policy_section(src)
    if not command.strip():
        raise UsageError(
            "--command must say how the checkpoint was trained (a committed policy is reproducible only with it)"
        )
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(command=command, source=str(src), kind=section["kind"], env_id=section["env_id"], obs=section["obs"])
    torch.save(dict(policy=section, **meta), dst)
    return dict(meta, bytes=dst.stat().st_size, path=str(dst))
