"""Input checks shared by the task and the CPU vector env.

Bad input gets an error that names the problem before it reaches a controller or a worker process:
gymnasium's ``AsyncVectorEnv`` shuts a worker down for good when it raises, so a vector env must reject
an action in the main process to stay usable, and ManiSkill's own errors (``TypeError: <class 'list'>``,
a bare ``IndexError``) do not say what was expected.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

_EXPECTED = "an array of real numbers (numpy array, torch tensor, or a list/tuple of floats)"


def _describe(x: Any) -> str:
    text = repr(x)
    return f"{type(x).__name__} {text[:80]}{'...' if len(text) > 80 else ''}"


def as_action_array(action: Any, what: str = "action") -> np.ndarray | torch.Tensor:
    """``action`` as a float numpy array or float torch tensor; lists and tuples of numbers are actions too.

    Raises TypeError for strings, objects, booleans and complex numbers (naming what was given) and
    ValueError for ragged nested lists. Shapes and finiteness are checked by the caller, which knows them.
    """
    if isinstance(action, torch.Tensor):
        if action.dtype.is_complex or action.dtype == torch.bool:
            raise TypeError(f"{what} must be {_EXPECTED}; got a torch tensor of dtype {action.dtype}")
        return action if action.dtype.is_floating_point else action.float()
    if isinstance(action, (str, bytes)) or not isinstance(action, (np.ndarray, np.generic, list, tuple, int, float)):
        raise TypeError(f"{what} must be {_EXPECTED}; got {_describe(action)}")
    try:
        arr = np.asarray(action)
    except ValueError as e:  # ragged nested lists
        raise ValueError(f"{what} is not a rectangular array of numbers ({e}); got {_describe(action)}") from None
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{what} must be {_EXPECTED}; got values of dtype {arr.dtype}: {_describe(action)}")
    return arr if arr.dtype.kind == "f" else arr.astype(np.float32)


def check_finite_actions(actions: np.ndarray, what: str = "actions") -> None:
    """ValueError naming the env indices (rows) whose action has a NaN or inf."""
    bad = ~np.isfinite(actions).reshape(len(actions), -1).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad).tolist()
        raise ValueError(f"{what} contain NaN or inf for env index {idx}: {actions[bad].tolist()}")


def check_env_idx(env_idx: Any, num_envs: int) -> np.ndarray:
    """Validated indices of the envs to reset, as a 1-D int64 array.

    Accepts a sequence, array or tensor of integer indices (or one int), or a boolean mask of length
    ``num_envs``. Raises TypeError for other element types and ValueError for an empty selection,
    indices outside ``0..num_envs-1`` and repeated indices.
    """
    if isinstance(env_idx, torch.Tensor):
        env_idx = env_idx.detach().cpu().numpy()
    if isinstance(env_idx, (str, bytes)) or not isinstance(env_idx, (np.ndarray, np.generic, list, tuple, range, int)):
        raise TypeError(
            f"options['env_idx'] must be integer env indices (list, array or tensor); got {_describe(env_idx)}"
        )
    idx = np.atleast_1d(np.asarray(env_idx))
    if idx.ndim != 1:
        raise ValueError(f"options['env_idx'] must be 1-D, got shape {idx.shape}")
    if idx.dtype == bool:
        if len(idx) != num_envs:
            raise ValueError(f"a boolean options['env_idx'] mask needs one entry per env ({num_envs}), got {len(idx)}")
        idx = np.flatnonzero(idx)
    elif len(idx) and idx.dtype.kind not in "iu":
        raise TypeError(f"options['env_idx'] must be integer env indices, got dtype {idx.dtype}: {_describe(env_idx)}")
    if len(idx) == 0:
        raise ValueError("options['env_idx'] selects no env; name at least one env to reset (or leave env_idx out)")
    out = idx[(idx < 0) | (idx >= num_envs)]
    if len(out):
        raise ValueError(
            f"options['env_idx'] {out.tolist()} out of range: valid env indices are 0..{num_envs - 1} "
            f"(num_envs={num_envs})"
        )
    if len(np.unique(idx)) != len(idx):
        raise ValueError(f"options['env_idx'] repeats an index: {idx.tolist()}")
    return idx.astype(np.int64)
