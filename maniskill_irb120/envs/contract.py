"""The env contract under bad input, shared by every IRB 120 task and the CPU vector env.

Bad input gets an error that names the problem before it reaches a controller or a worker process:
gymnasium's ``AsyncVectorEnv`` shuts a worker down for good when it raises, so a vector env must reject an
action in the main process to stay usable, and ManiSkill's own errors (``TypeError: <class 'list'>``, a bare
``IndexError``) do not say what was expected. :class:`EnvContractMixin` (before ManiSkill's BaseEnv) accepts
list and tuple actions, refuses other objects by name, and gives clear errors for obs modes, ``num_envs``,
reset indices and calls after ``close()``; ``render_mode="all"`` frames are padded to what video encoders take."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.envs.utils.observations import ALL_VISUAL_TEXTURES, parse_obs_mode_to_struct

from maniskill_irb120.errors import UsageError

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
    """UsageError (a ValueError) naming the env indices (rows) whose action has a NaN or inf."""
    bad = ~np.isfinite(actions).reshape(len(actions), -1).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad).tolist()
        raise UsageError(f"{what} contain NaN or inf for env index {idx}: {actions[bad].tolist()}")


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


VIDEO_BLOCK = 16  # render_mode="all" frames are padded to multiples of this (video encoders' macro block)


class EnvContractMixin:
    """Explicit ``BaseEnv.method(self, ...)`` calls instead of ``super()``: ManiSkill's ``Sim2RealEnv`` runs a
    task's methods with itself as ``self`` (``type(sim_env).step(real_env, action)``), where zero-argument
    ``super()`` raises ``TypeError``."""

    def step(self, action: Any):
        """ManiSkill's step, for lists and tuples of numbers too: BaseEnv takes only arrays, tensors and dicts
        and raises a bare ``TypeError: <class 'list'>``. Strings and other objects get a TypeError naming them."""
        self._check_open()
        if action is not None and not isinstance(action, dict):
            action = as_action_array(action)
        return BaseEnv.step(self, action)

    _closed: bool = False

    def close(self):
        self._closed = True
        BaseEnv.close(self)

    def render(self):
        self._check_open()
        return BaseEnv.render(self)

    def render_all(self):
        """ManiSkill's overview + hand-camera composite (512 x 596 by default) padded with black on the right
        and bottom to multiples of 16: video encoders (imageio/ffmpeg, macro_block_size 16) would otherwise
        rescale every frame, with a warning."""
        img = BaseEnv.render_all(self)
        h, w = img.shape[-3], img.shape[-2]
        ph, pw = -h % VIDEO_BLOCK, -w % VIDEO_BLOCK
        if not ph and not pw:
            return img
        pad = [(0, 0)] * (img.ndim - 3) + [(0, ph), (0, pw), (0, 0)]
        if isinstance(img, torch.Tensor):
            return torch.nn.functional.pad(img, [p for pair in reversed(pad) for p in pair])
        return np.pad(img, pad)

    def _check_open(self) -> None:
        """After ``close()`` ManiSkill has dropped the scene and agent: say so instead of failing on ``None``."""
        if self._closed:
            raise RuntimeError("the env is closed; make a new one with gym.make(...)")

    # obs modes ManiSkill 3.0.1 accepts by name: its SUPPORTED_OBS_MODES lacks "rgbd" and the single textures,
    # which parse_obs_mode_to_struct handles ("any_textures" there is a flag, not a mode)
    NAMED_OBS_MODES = ("rgbd", "state", "state_dict", "none", "sensor_data", "pointcloud", *ALL_VISUAL_TEXTURES)

    @classmethod
    def _check_obs_mode(cls, obs_mode: str | None) -> None:
        """ValueError listing every valid mode: ManiSkill asserts, or fails on ``str.split``, deep in its init."""
        if obs_mode is None or obs_mode in cls.NAMED_OBS_MODES:
            return
        try:  # combinations such as "rgb+depth" or "rgb+state_dict" (ManiSkill asserts on bad ones)
            if isinstance(obs_mode, str) and obs_mode:
                parse_obs_mode_to_struct(obs_mode)
                return
        except AssertionError:
            pass
        raise UsageError(
            f"obs_mode={obs_mode!r} is not supported; use one of {list(cls.NAMED_OBS_MODES)} or a '+'-joined "
            f"combination of {ALL_VISUAL_TEXTURES} with optional 'state' / 'state_dict', e.g. 'rgb+depth+state'"
        )

    @staticmethod
    def _check_batching(num_envs: Any, sim_backend: str) -> None:
        """Clear errors for ``num_envs``: ManiSkill fails on 0 with a bare IndexError, and on num_envs > 1
        without CUDA with ``failed to find device "cuda"``, which does not say that CPUs need worker processes."""
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise UsageError(f"num_envs must be a positive integer, got {num_envs!r}")
        if num_envs == 1:
            return
        on_gpu = sim_backend == "auto" or "cuda" in str(sim_backend) or sim_backend == "gpu"
        if not on_gpu or not torch.cuda.is_available():
            why = f"sim_backend={sim_backend!r} was given" if not on_gpu else "no CUDA GPU is available here"
            raise UsageError(
                f"num_envs={num_envs}: batched envs (num_envs > 1) need a CUDA GPU (sim_backend='physx_cuda'), and "
                f'{why}. On CPUs use maniskill_irb120.make_vec_env(env_id, num_envs, backend="cpu"): one worker '
                "process per env behind the same batched interface; the workers import your script again, so in a "
                'script call it under if __name__ == "__main__":'
            )

    def _checked_reset_options(self, options: dict | None) -> dict | None:
        """``options["env_idx"]`` checked (ValueError naming the valid range instead of a bare IndexError) and
        handed on as an index tensor on the env's device."""
        if options is None:
            return None
        if not isinstance(options, dict):
            raise TypeError(f"reset options must be a dict, got {type(options).__name__}")
        if "env_idx" not in options:
            return options
        idx = check_env_idx(options["env_idx"], self.num_envs)
        return {**options, "env_idx": torch.as_tensor(idx, device=self.device)}
