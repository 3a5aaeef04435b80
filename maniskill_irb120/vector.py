"""One vector-env interface for GPU-batched and CPU process-parallel simulation.

ManiSkill batches envs inside one process only on ``physx_cuda``. On a CPU-only machine the same
training code gets N worker processes (gymnasium ``AsyncVectorEnv`` of ``CPUGymWrapper`` envs, shared
memory, same-step autoreset) behind the exact interface of ``ManiSkillVectorEnv``: batched torch obs
dicts, torch rewards/terminations, auto-reset with ``final_observation`` / ``final_info`` /
``_final_info``, partial resets via ``options={"env_idx": ...}`` and optional ``episode`` metrics.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.envs.contract import as_action_array, check_env_idx, check_finite_actions


def _to_torch(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_torch(v) for k, v in x.items()}
    if isinstance(x, np.ndarray) and x.dtype != object:
        return torch.from_numpy(np.ascontiguousarray(x))
    return x


def _to_host(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _to_host(v) for k, v in x.items()}
    if isinstance(x, torch.Tensor):
        return x.cpu()
    return x


class OnHost(gym.vector.VectorWrapper):
    """A batched env seen from training code that keeps its data in host memory (agents.dagger's dataset,
    agents.sac's replay): observations, rewards, flags and infos (``final_info`` too) come back as CPU tensors,
    actions go to the env's device. On a GPU-batched env that is one copy per step; on a CPU env, nothing."""

    def __init__(self, env: gym.vector.VectorEnv):
        super().__init__(env)
        # from the base env: a VectorWrapper between it and OnHost does not forward ``device``
        self.env_device = torch.device(getattr(env.unwrapped, "device", "cpu"))
        self.device = torch.device("cpu")

    def reset(self, *, seed: Optional[int | list[int]] = None, options: Optional[dict] = None):
        if options and "env_idx" in options:
            # ManiSkill indexes its device-side buffers with env_idx as given; host indices would mix devices
            options = {**options, "env_idx": torch.as_tensor(options["env_idx"], device=self.env_device)}
        obs, info = self.env.reset(seed=seed, options=options)
        return _to_host(obs), _to_host(info)

    def step(self, actions):
        if isinstance(actions, torch.Tensor):
            actions = actions.to(self.env_device)
        return tuple(_to_host(x) for x in self.env.step(actions))


def _select(where: torch.Tensor, new: Any, old: Any) -> Any:
    """Per-env choice between two batched (possibly nested) tensors: ``new`` where ``where``."""
    if isinstance(new, dict):
        return {k: _select(where, new[k], old[k]) if k in old else new[k] for k in new}
    if isinstance(new, torch.Tensor) and isinstance(old, torch.Tensor) and new.shape == old.shape:
        mask = where.view(-1, *([1] * (new.dim() - 1)))
        return torch.where(mask, new, old)
    return new


def _make_worker_env(
    env_id: str,
    env_kwargs: dict,
    wrappers: Sequence[Callable],
    ignore_terminations: bool,
    lp_num_threads: Optional[int],
) -> gym.Env:
    # lavapipe reads this when the render device is created, i.e. inside gym.make below
    if lp_num_threads:
        os.environ.setdefault("LP_NUM_THREADS", str(lp_num_threads))
    # one worker per core: torch's intra-op threads would only spin against the other workers
    torch.set_num_threads(1)
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import maniskill_irb120  # noqa: F401  (registers our envs in the worker)

    env = gym.make(env_id, num_envs=1, **env_kwargs)
    for w in wrappers:
        env = w(env)
    return CPUGymWrapper(env, ignore_terminations=ignore_terminations)


def _stack_final_obs(final_obs: np.ndarray, like: Any, done: np.ndarray) -> Any:
    """Gymnasium keeps final observations as an object array of per-env obs; batch the done ones."""
    if isinstance(like, dict):
        out = {}
        for k in like:
            # filled element by element: np.array(list, dtype=object) would split equal-shaped arrays
            # into an object array of scalars (always the case with one env, or all envs done at once)
            sub = np.empty(len(final_obs), dtype=object)
            for j, o in enumerate(final_obs):
                sub[j] = None if o is None else o[k]
            out[k] = _stack_final_obs(sub, like[k], done)
        return out
    out = like.clone()
    for i in np.flatnonzero(done):
        out[i] = torch.as_tensor(np.asarray(final_obs[i]))
    return out


def _strip_masks(info: dict) -> dict:
    return {k: (_strip_masks(v) if isinstance(v, dict) else v) for k, v in info.items() if not k.startswith("_")}


class CPUVectorEnv(gym.vector.VectorEnv):
    """N single-env ManiSkill workers in processes, with ManiSkillVectorEnv's batched torch interface."""

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        wrappers: Sequence[Callable] = (),
        ignore_terminations: bool = False,
        record_metrics: bool = False,
        context: str = "forkserver",
        lp_num_threads: Optional[int] = 1,
        **env_kwargs,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if env_kwargs.get("sim_backend", "physx_cpu") not in ("physx_cpu", "cpu", "auto"):
            raise ValueError(f"CPUVectorEnv workers run physx_cpu, got sim_backend={env_kwargs['sim_backend']!r}")
        env_kwargs.pop("sim_backend", None)
        fn = functools.partial(
            _make_worker_env, env_id, env_kwargs, tuple(wrappers), ignore_terminations, lp_num_threads
        )
        # gymnasium builds one env in this process to read the spaces (AsyncVectorEnv's dummy env), i.e. runs the
        # worker's setup here too: without the restore, every trainer's learner was left on one torch thread
        threads, lp = torch.get_num_threads(), os.environ.get("LP_NUM_THREADS")
        try:
            self._venv = gym.vector.AsyncVectorEnv(
                [fn] * num_envs,
                context=context,
                shared_memory=True,
                autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
            )
        finally:
            torch.set_num_threads(threads)
            if lp is None:
                os.environ.pop("LP_NUM_THREADS", None)
            else:
                os.environ["LP_NUM_THREADS"] = lp
        self.num_envs = num_envs
        self.ignore_terminations = ignore_terminations
        self.record_metrics = record_metrics
        self.single_observation_space = self._venv.single_observation_space
        self.single_action_space = self._venv.single_action_space
        self.observation_space = self._venv.observation_space
        self.action_space = self._venv.action_space
        self.metadata = dict(self._venv.metadata, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        self.spec = None
        self.device = torch.device("cpu")
        self.success_once = torch.zeros(num_envs, dtype=torch.bool)
        self.fail_once = torch.zeros(num_envs, dtype=torch.bool)
        self.returns = torch.zeros(num_envs, dtype=torch.float32)
        self.elapsed_steps = torch.zeros(num_envs, dtype=torch.int32)

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: Optional[int | list[int]] = None, options: Optional[dict] = None):
        self._check_usable()
        options = dict(options or {})
        mask = np.ones(self.num_envs, dtype=bool)
        if "env_idx" in options:
            idx = check_env_idx(options.pop("env_idx"), self.num_envs)
            mask[:] = False
            mask[idx] = True
            options["reset_mask"] = mask
        obs, info = self._venv.reset(seed=seed, options=options or None)
        m = torch.from_numpy(mask)
        self.success_once[m] = False
        self.fail_once[m] = False
        self.returns[m] = 0
        self.elapsed_steps[m] = 0
        return _to_torch(obs), _to_torch(_strip_masks(info))

    def step(self, actions):
        actions = self._checked_actions(actions)
        obs_np, rew, term, trunc, info_np = self._venv.step(actions)
        obs = _to_torch(obs_np)
        rew = torch.from_numpy(np.asarray(rew, dtype=np.float32))
        term = torch.from_numpy(np.asarray(term, dtype=bool))
        trunc = torch.from_numpy(np.asarray(trunc, dtype=bool))
        dones = term | trunc
        done_np = dones.numpy()
        infos = _to_torch(_strip_masks({k: v for k, v in info_np.items() if k not in ("final_obs", "final_info")}))
        # the step's own info for every env: the final one where an episode ended
        step_info = infos
        if done_np.any():
            final_info = _to_torch(_strip_masks(info_np["final_info"]))
            step_info = _select(dones, final_info, infos)
        self.returns += rew
        self.elapsed_steps += 1
        if self.record_metrics:
            episode = {}
            if "success" in step_info:
                self.success_once |= step_info["success"].bool()
                episode["success_once"] = self.success_once.clone()
            if "fail" in step_info:
                self.fail_once |= step_info["fail"].bool()
                episode["fail_once"] = self.fail_once.clone()
            episode["return"] = self.returns.clone()
            episode["episode_len"] = self.elapsed_steps.clone()
            episode["reward"] = episode["return"] / episode["episode_len"]
            if self.ignore_terminations:
                for k in ("success", "fail"):
                    if k in step_info:
                        episode[f"{k}_at_end"] = step_info[k].clone()
            step_info["episode"] = episode
            infos["episode"] = episode
        if done_np.any():
            infos["final_observation"] = _stack_final_obs(info_np["final_obs"], obs, done_np)
            infos["final_info"] = step_info
            infos["_final_info"] = dones
            infos["_final_observation"] = dones
            infos["_elapsed_steps"] = dones
            self.success_once[dones] = False
            self.fail_once[dones] = False
            self.returns[dones] = 0
            self.elapsed_steps[dones] = 0
        return obs, rew, term, trunc, infos

    def call(self, name: str, *args, **kwargs):
        self._check_usable()
        return self._venv.call(name, *args, **kwargs)

    def render(self):
        """Each worker's ``render()``; checked here first, since a worker that raises is lost for good."""
        self._check_usable()
        if self._venv.render_mode is None:
            raise RuntimeError(
                "render_mode is not set: pass render_mode='rgb_array' (or 'sensors', 'all') to make_vec_env"
            )
        return self._venv.call("render")

    # ------------------------------------------------------------------ input checks
    def _checked_actions(self, actions: Any) -> np.ndarray:
        """The batch as float32 numpy, or a clear error *before* dispatch: a worker that raises is shut down
        by gymnasium for good, and every later call would fail with ``'NoneType' object has no attribute 'send'``."""
        self._check_usable()
        actions = as_action_array(actions, "actions")
        if isinstance(actions, torch.Tensor):
            actions = actions.detach().cpu().numpy()
        actions = np.asarray(actions, dtype=np.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions have shape {actions.shape}, expected {self.action_space.shape}")
        check_finite_actions(actions)
        return actions

    def _check_usable(self) -> None:
        """RuntimeError after ``close()`` or once a worker died, instead of gymnasium's pipe errors."""
        if self.closed:
            raise RuntimeError("the vector env is closed; make a new one with make_vec_env(...)")
        dead = [i for i, pipe in enumerate(self._venv.parent_pipes) if pipe is None]
        if dead:
            raise RuntimeError(
                f"worker(s) {dead} of this vector env were shut down after raising an error (see the "
                "earlier traceback); close() it and make a new one with make_vec_env(...)"
            )

    def close_extras(self, **kwargs):
        if hasattr(self, "_venv"):  # not when __init__ failed before the workers existed
            self._venv.close(**kwargs)


def make_vec_env(
    env_id: str,
    num_envs: int,
    *,
    backend: str = "auto",
    wrappers: Sequence[Callable] = (),
    ignore_terminations: bool = False,
    record_metrics: bool = True,
    **env_kwargs,
) -> gym.vector.VectorEnv:
    """The front door for batched training code; it need not care which backend it got.

    ``backend``: ``"auto"`` (GPU-batched ``physx_cuda`` when CUDA is available, else CPU processes),
    ``"gpu"``, ``"cpu"`` (worker processes) or ``"inprocess"`` (one CPU env, num_envs must be 1).
    ``wrappers`` are applied to each ManiSkill env before batching (e.g. FlattenRGBDObservationWrapper).
    Seeding: ``reset(seed=s)`` seeds worker i with ``s + i`` on CPU; the GPU env derives its own per-env
    seeds from ``s``, so the two backends draw different (equally distributed) initial states.
    """
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    if backend not in ("auto", "gpu", "cpu", "inprocess"):
        raise ValueError(f"unknown backend {backend!r}; use 'auto', 'gpu', 'cpu' or 'inprocess'")
    if backend == "auto":
        backend = "gpu" if torch.cuda.is_available() else ("inprocess" if num_envs == 1 else "cpu")
    if backend in ("gpu", "inprocess"):
        # the backend decides the sim backend; a consistent sim_backend kwarg is accepted, others named
        sim = "physx_cuda" if backend == "gpu" else "physx_cpu"
        given = env_kwargs.pop("sim_backend", sim)
        if given not in (sim, "auto", "gpu" if backend == "gpu" else "cpu"):
            raise ValueError(f"backend={backend!r} runs {sim}, got sim_backend={given!r}")
    if backend == "gpu":
        if not torch.cuda.is_available():
            raise ValueError("backend='gpu' needs CUDA; none is available here (use backend='cpu')")
        env = gym.make(env_id, num_envs=num_envs, sim_backend="physx_cuda", **env_kwargs)
    elif backend == "inprocess":
        if num_envs != 1:
            raise ValueError("backend='inprocess' runs one CPU env; use backend='cpu' for num_envs > 1")
        env = gym.make(env_id, num_envs=1, sim_backend="physx_cpu", **env_kwargs)
    else:
        return CPUVectorEnv(
            env_id,
            num_envs,
            wrappers=wrappers,
            ignore_terminations=ignore_terminations,
            record_metrics=record_metrics,
            **env_kwargs,
        )
    for w in wrappers:
        env = w(env)
    return ManiSkillVectorEnv(
        env, num_envs, auto_reset=True, ignore_terminations=ignore_terminations, record_metrics=record_metrics
    )
