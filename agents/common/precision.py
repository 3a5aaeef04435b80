"""Mixed precision for the learner's camera encoder (``--precision``).

On a CPU with native bfloat16 (AVX512-BF16 or AMX: AMD Zen 4, Intel Cooper Lake and Sapphire Rapids on),
oneDNN runs the camera encoder's convolutions about twice as fast under bf16 autocast as in float32, and those
convolutions are most of a camera update; trainers run only the encoder under it. Weights, optimiser state, the
heads, the losses, the keypoints' spatial softmax and the proprioception MLP stay float32 (the last two opt out
of autocast in ``maniskill_irb120.policies.nets``), so a checkpoint is the same float32 policy either way and
evaluation, export and the real robot never run in bf16. Without native support bf16 is emulated and slower
than float32: ``bf16`` is then refused and ``auto`` means float32. On a GPU ``auto`` means float32 too: this
small encoder at the recipe's batch of 64 is bound by kernel launches there, not arithmetic, and bf16 autocast
only adds casts (``benchmarks/learner_speed.py --device cuda``, RESULTS.md's GPU section); ``bf16`` stays
available to try on bigger batches."""

from __future__ import annotations

import contextlib

import torch

PRECISIONS = ("fp32", "bf16", "auto")


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 natively (CPU: oneDNN's check for AVX512-BF16/AMX)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type != "cpu":
        return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch build without oneDNN
        return False


def resolve_precision(name: str, device: torch.device) -> str:
    """``fp32`` or ``bf16`` for ``--precision name`` on ``device``."""
    if name not in PRECISIONS:
        raise ValueError(f"--precision {name!r} is not one of {PRECISIONS}")
    if name == "auto":
        return "bf16" if device.type == "cpu" and native_bf16(device) else "fp32"
    if name == "bf16" and not native_bf16(device):
        raise ValueError(
            f"--precision bf16: {device} has no native bfloat16 (it would be emulated, slower than fp32); "
            "use --precision fp32 or auto"
        )
    return name


def autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The context the learner's encoder runs in: bf16 autocast, or nothing for fp32."""
    if precision == "fp32":
        return contextlib.nullcontext()
    if precision != "bf16":
        raise ValueError(f"precision {precision!r} is not resolved (fp32 or bf16; see resolve_precision)")
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
