"""The envs RLlib samples from: any registered task as a single gymnasium env (ManiSkill's ``CPUGymWrapper``,
numpy observations) for RLlib's own sync vectorisation, or, opt-in, an already-batched ManiSkill vector env
(GPU ``physx_cuda``, or our CPU worker env) behind :class:`NextStepAutoreset` for RLlib's vector entry point."""

from __future__ import annotations

from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch

ENV_NAME = "maniskill_irb120"
"""the name :func:`register` gives the creator in Ray's registry (``config.environment(ENV_NAME, ...)``)"""

_CONFIG_KEYS = {"env_id", "obs", "env_kwargs", "vector_backend", "num_envs"}


def _env_kwargs(cfg: dict) -> dict:
    kwargs = dict(obs_mode=cfg.get("obs", "state"), control_mode="pd_ee_delta_tool", reward_mode="normalized_dense")
    if kwargs["obs_mode"] not in ("state", "rgbd"):
        raise ValueError(f"env_config obs={kwargs['obs_mode']!r}: use 'state' or 'rgbd'")
    kwargs.update(cfg.get("env_kwargs") or {})
    if kwargs["obs_mode"] == "state" and "render_mode" not in kwargs:
        kwargs.setdefault("render_backend", "none")  # no renderer needed: no Vulkan device in env runners
    return kwargs


def make_env(env_config: dict) -> gym.Env:
    """RLlib's env creator. ``env_config``: ``env_id``, ``obs`` ('state' | 'rgbd'), ``env_kwargs`` (anything
    ``gym.make`` of the task takes), ``vector_backend`` (None: one env; 'gpu' or 'cpu': a batched env of
    ``num_envs`` behind :class:`NextStepAutoreset`, for ``gym_env_vectorize_mode=VECTOR_ENTRY_POINT``)."""
    unknown = set(env_config) - _CONFIG_KEYS
    if unknown:
        raise ValueError(f"unknown env_config key(s) {sorted(unknown)}; known: {sorted(_CONFIG_KEYS)}")
    torch.set_num_threads(1)  # one env per env-runner core; torch threads would only contend
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import maniskill_irb120  # noqa: F401  (registers the tasks in this process)

    env_id = env_config.get("env_id", "TableClearing-IRB120-v1")
    kwargs = _env_kwargs(env_config)
    wrappers = [FlattenRGBDObservationWrapper] if kwargs["obs_mode"] == "rgbd" else []
    backend = env_config.get("vector_backend")
    if backend is not None:
        from maniskill_irb120.vector import make_vec_env

        num_envs = int(env_config.get("num_envs", 1))
        venv = make_vec_env(env_id, num_envs, backend=backend, wrappers=wrappers, record_metrics=False, **kwargs)
        return NextStepAutoreset(venv)
    env = gym.make(env_id, num_envs=1, **kwargs)
    for w in wrappers:
        env = w(env)
    return CPUGymWrapper(env)


def register() -> str:
    """Register :func:`make_env` with Ray under :data:`ENV_NAME` (in this process; env runners get the
    creator with the pickled config)."""
    from ray.tune.registry import register_env

    register_env(ENV_NAME, make_env)
    return ENV_NAME


def _numpy(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _numpy(v) for k, v in x.items()}
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return x


def _splice(where: np.ndarray, new: Any, old: Any) -> Any:
    """``new`` for envs ``where``, ``old`` for the rest (nested dicts of batched arrays)."""
    if isinstance(new, dict):
        return {k: _splice(where, new[k], old[k]) for k in new}
    mask = where.reshape(-1, *([1] * (np.ndim(new) - 1)))
    return np.where(mask, new, old)


class NextStepAutoreset(gym.vector.VectorEnv):
    """A same-step-autoreset batched env (``ManiSkillVectorEnv``, ``make_vec_env``) as gymnasium's next-step
    autoreset, which RLlib's env runner assumes, with numpy in and out.

    Same step (ManiSkill): the step that ends episode i returns the *next* episode's first obs, the last one in
    ``infos['final_observation']``. Next step (gymnasium, RLlib): that step returns the last obs; the following
    step ignores env i's action and returns a fresh first obs with reward 0 and no done flag. A batched GPU
    env cannot skip one env's physics step, so that following step steps everyone and then resets the envs
    that had ended (a partial reset), so the obs returned is a true first obs.
    """

    def __init__(self, venv: gym.vector.VectorEnv):
        self.venv = venv
        self.num_envs = venv.num_envs
        self.single_observation_space = venv.single_observation_space
        self.single_action_space = venv.single_action_space
        self.observation_space = venv.observation_space
        self.action_space = venv.action_space
        self.metadata = dict(getattr(venv, "metadata", {}), autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)
        self.spec = None
        self._pending = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: Optional[int | list[int]] = None, options: Optional[dict] = None):
        if isinstance(seed, list):  # RLlib passes one seed per env; a batched env takes the first and derives
            seed = seed[0]
        obs, info = self.venv.reset(seed=seed, options=options)
        self._pending[:] = False
        return _numpy(obs), self._info(info)

    def step(self, actions):
        obs, rew, term, trunc, info = self.venv.step(torch.as_tensor(np.asarray(actions, dtype=np.float32)))
        obs, rew = _numpy(obs), _numpy(rew).astype(np.float32)
        term, trunc = _numpy(term).astype(bool), _numpy(trunc).astype(bool)
        done = term | trunc
        ended = done & ~self._pending
        step_info = self._info(info)
        if ended.any() and "final_observation" in info:  # the last obs and info, not the next episode's first
            obs = _splice(ended, _numpy(info["final_observation"]), obs)
            last = self._info(info.get("final_info", {}))
            step_info = {k: _splice(ended, last[k], v) if k in last else v for k, v in step_info.items()}
        info = step_info
        if self._pending.any():
            idx = np.flatnonzero(self._pending)
            device = getattr(self.venv, "device", "cpu")  # ManiSkill indexes its GPU state with it as given
            first, first_info = self.venv.reset(options=dict(env_idx=torch.as_tensor(idx, device=device)))
            obs = _splice(self._pending, _numpy(first), obs)
            first_info = self._info(first_info)
            info = {k: _splice(self._pending, first_info[k], v) if k in first_info else v for k, v in info.items()}
            rew[self._pending] = 0.0
            term[self._pending] = trunc[self._pending] = False
        self._pending = (term | trunc).copy()
        return obs, rew, term, trunc, info

    def _info(self, info: dict) -> dict:
        """Per-env entries only (RLlib splits the dict into one info per env); the final obs and ManiSkill's
        episode summaries are dropped: next-step autoreset reports the last step as an ordinary step."""
        skip = ("final_observation", "final_info", "episode")
        out = {}
        for k, v in info.items():
            v = _numpy(v)
            if k not in skip and not k.startswith("_") and np.ndim(v) >= 1 and len(v) == self.num_envs:
                out[k] = v
        return out

    def close_extras(self, **kwargs):
        self.venv.close()
