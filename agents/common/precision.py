"""Mixed precision for the learner's camera encoder (``--precision``): bf16 autocast over the encoder's
convolutions where the CPU has native bfloat16 (about twice as fast there), everything else and every checkpoint
float32, so evaluation, export and the robot never run in bf16. Without native support ``bf16`` is refused and
``auto`` means float32; on a GPU ``auto`` means float32 too (the small encoder is launch-bound there).
See docs/training.md."""

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
