"""Checkpoint plumbing every trainer shares: the run's flags as JSON, atomic writes, format-checked reads that bring
an older checkpoint up to date (:func:`migrate`, the one place that knows the older layouts) and the RNG state a
resumed run continues from. Every checkpoint written carries ``format_version`` (:data:`FORMAT_VERSION`).
See docs/training.md."""

from __future__ import annotations

import json
import os
import random
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from maniskill_irb120.errors import UsageError
from maniskill_irb120.policies.section import read_checkpoint


def args_json(args) -> dict:
    return json.loads(json.dumps(asdict(args), default=str))


def atomic_save(obj: Any, path: Path) -> None:
    """torch.save to a temporary file, then rename: a crash never leaves a truncated checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


FORMAT_VERSION = 2
"""the layout of a trainer's checkpoint; a checkpoint without ``format_version`` is version 1"""

PPO_FORMAT = "maniskill_irb120.ppo/1"

PPO_SIGNATURE_V1 = dict(residual=False, state_net="shared", obs_norm=False, logstd="param")
"""what a version-1 PPO checkpoint's signature may lack: the options added since, at the value it was trained with"""


def migrate(ckpt: dict) -> dict:
    """``ckpt`` (a trainer's checkpoint, any version) in the current layout, changed in place and returned.
    Version 1 to 2: the run's ``args`` always present, under the flags' current names (``--resume`` reads them);
    PPO's step counter is ``env_steps`` as every trainer's (its ``global_step`` renamed, in the selected
    checkpoint's record too), its signature lists every option and its args name the action frame (``tool``, the
    only one then)."""
    version = ckpt.get("format_version", 1)
    if version > FORMAT_VERSION:
        raise ValueError(f"checkpoint format_version {version} is newer than this code's {FORMAT_VERSION}")
    if version < 2:
        args = ckpt.setdefault("args", {})
        if args.get("total_env_steps") is None and args.get("total_timesteps") is not None:
            args["total_env_steps"] = args["total_timesteps"]
        if args.get("max_minutes") is None and args.get("budget_min") is None and args.get("max_wall_s") is not None:
            args["max_minutes"] = args["max_wall_s"] / 60
        if "num_eval_episodes" in args:
            args["eval_freq_episodes"] = args["num_eval_episodes"]
        for gone in ("total_timesteps", "max_wall_s", "num_eval_episodes", "partial_reset"):
            args.pop(gone, None)
        if ckpt.get("format") == PPO_FORMAT:
            ckpt["signature"] = dict(PPO_SIGNATURE_V1, **ckpt.get("signature", {}))
            ckpt["args"].setdefault("action_frame", "tool")
            counters = ckpt.get("counters", {})
            if "global_step" in counters:
                counters["env_steps"] = counters.pop("global_step")
            if isinstance(counters.get("best"), dict) and "global_step" in counters["best"]:
                counters["best"]["env_steps"] = counters["best"].pop("global_step")
    ckpt["format_version"] = FORMAT_VERSION
    return ckpt


def load_torch(path: Path, fmt: str, what: str) -> dict:
    """A checkpoint written by ``what`` in format ``fmt``, migrated to the current layout, or an error that says
    why not."""
    ckpt = read_checkpoint(path)
    if not isinstance(ckpt, dict) or ckpt.get("format") != fmt:
        found = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt)
        raise ValueError(f"checkpoint {path} was not written by {what} (format {found})")
    return migrate(ckpt)


def load_for_evaluation(path: Path, fmt: str, what: str, kind: str) -> dict:
    """For ``--evaluate``: a checkpoint written by ``what``, or a policy exported from one (``maniskill-irb120
    export-policy``: the committed ones), whose section then stands in for the arguments the evaluation checks
    (it has no trainer state to resume from)."""
    ckpt = read_checkpoint(path)
    exported = isinstance(ckpt, dict) and "format" not in ckpt and "command" in ckpt
    if not (exported and isinstance(ckpt.get("policy"), dict)):
        return load_torch(path, fmt, what)
    section = ckpt["policy"]
    if section.get("kind") != kind:
        raise ValueError(f"{path} is an exported {section.get('kind')} policy, not one {what} trains")
    keys = ("env_id", "obs", "action_frame", "obs_without", "env_kwargs")
    return dict(ckpt, args={k: section.get(k) for k in keys}, exported=True)


def signature_mismatch(what: str, saved: dict, signature: dict, args) -> UsageError:
    """The error for a checkpoint whose networks (``saved``, its ``signature``) differ from this run's: each
    differing entry with both values, and where the entry is one of the trainer's flags (a field of ``args``), the
    flag that builds the checkpoint's network, so the fix is in the one line."""
    parts = []
    for key in sorted(saved.keys() | signature.keys()):
        theirs, ours = saved.get(key), signature.get(key)
        if theirs == ours:
            continue
        flag = "--" + key.replace("_", "-")
        if hasattr(args, key) and isinstance(theirs, bool):
            fix = f" (pass {flag if theirs else '--no-' + flag[2:]})"
        elif hasattr(args, key) and theirs is not None:
            fix = f" (pass {flag} {theirs})"
        else:
            fix = ""
        parts.append(f"{key} {theirs!r} in the checkpoint, {ours!r} in this run{fix}")
    return UsageError(f"{what}: its networks differ from this run's: {'; '.join(parts)}")


def rng_state() -> dict:
    s = dict(python=random.getstate(), numpy=np.random.get_state(), torch=torch.get_rng_state())
    if torch.cuda.is_available():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def set_rng_state(s: dict) -> None:
    random.setstate(s["python"])
    np.random.set_state(s["numpy"])
    torch.set_rng_state(s["torch"])
    if "cuda" in s and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])
