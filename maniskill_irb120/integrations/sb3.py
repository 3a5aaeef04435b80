"""Stable-Baselines3 on the tasks: an SB3 ``VecEnv`` on either backend, with SB3's episode statistics.

    from stable_baselines3 import PPO
    from maniskill_irb120.integrations.sb3 import make_sb3_vec_env

    venv = make_sb3_vec_env("GraspLift-IRB120-v1", num_envs=2, obs="rgbd")  # or obs="state"
    PPO("MultiInputPolicy", venv).learn(10_000)                             # "MlpPolicy" on state

:class:`IRB120SB3VecEnv` is ManiSkill's own ``ManiSkillSB3VectorEnv`` (its construction, seeding, action hand-off
and close are used as they are) over :func:`~maniskill_irb120.integrations.observations.make_vector_env`:
``backend="cpu"`` steps the envs in worker processes (env 0 in this process), ``backend="gpu"`` batches them on
``physx_cuda`` (unverified here: it needs a GPU and a CUDA PhysX; the code path is the CPU one's, with the tensors
on the GPU). What it does differently from ManiSkill's wrapper, and why:

- observations: ManiSkill's calls ``obs.cpu().numpy()``, which fails on a dict; here every key converts, so the
  camera's ``{"image", "state"}`` observation (integrations/observations.py) reaches ``MultiInputPolicy``.
- episode statistics: ManiSkill's puts ``"episode": {"r": all envs' running returns, "l": ...}`` into every info on
  every step, so SB3's ``ep_rew_mean`` averages arrays of unfinished episodes. Here, as SB3's ``Monitor`` does, an
  env's info carries ``"episode": {"r", "l", "t"}`` (scalars) only on the step its episode ended, with
  ``"is_success"`` (the task's ``success`` on that step), which SB3 logs as ``rollout/success_rate``.
- resets: the vector env resets an ended env in the same step (a partial reset: the others run on); the info of
  that env carries ``"terminal_observation"`` (the episode's last observation, as SB3's own VecEnvs) and
  ``"TimeLimit.truncated"`` (truncated, not terminated), which SB3 uses to bootstrap a cut-off episode.
- ``get_attr``/``env_method``: ManiSkill's forward to methods its env does not have; here they reach each CPU
  env (or the one batched GPU env).
- torch threads: one while the CPU envs step (env 0 steps in this process, beside the workers), the learner's
  (``learner_threads``) between steps, while the workers wait: ``observations.StepThreads`` says why.
- its input: a vector env with ``num_envs``. ManiSkill's own example hands it ``gym.make(...)``, whose
  ``TimeLimitWrapper`` has no ``num_envs`` (https://github.com/mani-skill/ManiSkill/issues/1404).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.integrations.observations import (
    CONTROL_MODE,
    StepThreads,
    learner_threads_for,
    make_single_env,
    wrapped_vector_env,
)
from maniskill_irb120.integrations.progress import (
    EVERY_S,
    HELD_OUT_SEED,
    VALIDATION_SEED,
    Heartbeat,
    Progress,
    held_out_success,
)
from maniskill_irb120.integrations.selection import ValidationSelection

try:
    from mani_skill.vector.wrappers.sb3 import ManiSkillSB3VectorEnv
    from stable_baselines3.common.callbacks import BaseCallback
except ModuleNotFoundError as e:  # pragma: no cover - the extra is missing
    if e.name != "stable_baselines3":
        raise
    raise ModuleNotFoundError(
        "maniskill_irb120.integrations.sb3 needs Stable-Baselines3: pip install -e '.[sb3]'", name=e.name
    ) from e


def _numpy(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _numpy(v) for k, v in x.items()}
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _row(x: Any, i: int) -> Any:
    return {k: _row(v, i) for k, v in x.items()} if isinstance(x, dict) else x[i].copy()


def _write_rows(dst: Any, src: Any, idx: np.ndarray) -> None:
    if isinstance(dst, dict):
        for k in dst:
            _write_rows(dst[k], src[k], idx)
    else:
        dst[idx] = src[idx]


class IRB120SB3VecEnv(ManiSkillSB3VectorEnv):
    """An SB3 ``VecEnv`` over a batched env from ``make_vector_env`` (see the module doc)."""

    def __init__(self, env: gym.vector.VectorEnv, learner_threads: int = 1):
        self._threads = StepThreads(env, learner_threads)  # torch's threads around each step (module doc)
        # SB3's VecEnv.__init__ reads render_mode through get_attr, i.e. through the env: set it first (ManiSkill's
        # wrapper sets it after, and SB3 then warns that the env has no render_mode)
        self._env = env
        super().__init__(env)
        self.episode_returns = self.episode_returns.cpu()
        self.episode_lengths = self.episode_lengths.cpu().long()

    @property
    def vector_env(self) -> gym.vector.VectorEnv:
        """The batched torch env underneath (``CPUVectorEnv`` or ManiSkill's ``ManiSkillVectorEnv``)."""
        return self._env

    def reset(self):
        with self._threads.stepping():
            obs, _ = self._env.reset(seed=self._last_seed, options=self._options[0] or None)
        self._last_seed = None  # a seed from seed() applies to the next reset only
        self._reset_options()
        self.episode_returns.zero_()
        self.episode_lengths.zero_()
        return _numpy(obs)

    def step_wait(self):
        with self._threads.stepping():
            obs, rew, term, trunc, infos = self._env.step(self.last_actions)
        rew, term, trunc = rew.cpu().float(), term.cpu().bool(), trunc.cpu().bool()
        dones = term | trunc
        self.episode_returns += rew
        self.episode_lengths += 1
        obs_np = _numpy(obs)
        new_infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            final_obs = _numpy(infos["final_observation"])
            final_info = infos["final_info"]
            success = final_info.get("success")
            success = success.cpu().bool() if isinstance(success, torch.Tensor) else None
            t = round(time.time() - self.t_start, 6)
            for i in torch.nonzero(dones).flatten().tolist():
                info = new_infos[i]
                info["terminal_observation"] = _row(final_obs, i)
                info["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
                info["episode"] = {"r": float(self.episode_returns[i]), "l": int(self.episode_lengths[i]), "t": t}
                if success is not None:
                    info["is_success"] = bool(success[i])
            self.episode_returns[dones] = 0
            self.episode_lengths[dones] = 0
        return obs_np, rew.numpy(), dones.numpy(), new_infos

    # ------------------------------------------------------------------ attributes
    def _each(self, indices) -> list[int]:
        return list(self._get_indices(indices))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        from maniskill_irb120.vector import CPUVectorEnv

        idx = self._each(indices)
        env = self.__dict__.get("_env")
        if env is None:
            raise AttributeError(attr_name)
        if isinstance(env, CPUVectorEnv):
            values = [a for a in env.call("get_wrapper_attr", attr_name)]
            return [values[i] for i in idx]
        # one batched env on the GPU: its attribute is every env's
        value = getattr(env, attr_name) if hasattr(env, attr_name) else getattr(env.unwrapped, attr_name)
        return [value for _ in idx]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise NotImplementedError(
            "set_attr: the envs run in worker processes (or as one batched GPU env); pass settings to "
            "make_sb3_vec_env(..., env_kwargs=...) instead"
        )

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        from maniskill_irb120.vector import CPUVectorEnv

        idx = self._each(indices)
        if isinstance(self._env, CPUVectorEnv):
            values = list(self._env.call(method_name, *method_args, **method_kwargs))
            return [values[i] for i in idx]
        out = getattr(self._env.unwrapped, method_name)(*method_args, **method_kwargs)
        return [out for _ in idx]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices=None) -> list[bool]:
        """False: no env is wrapped in SB3's ``Monitor`` (this VecEnv reports the episodes itself)."""
        return [False for _ in self._each(indices)]


def make_sb3_vec_env(
    env_id: str,
    num_envs: int = 2,
    obs: str = "state",
    *,
    backend: str = "auto",
    reward_mode: Optional[str] = None,
    control_mode: Optional[str] = CONTROL_MODE,
    seed: Optional[int] = None,
    wrappers: Sequence[Callable[[gym.Env], gym.Env]] = (),
    env_kwargs: Optional[dict] = None,
    learner_threads: Optional[int] = None,
) -> IRB120SB3VecEnv:
    """``num_envs`` envs of ``env_id`` as an SB3 ``VecEnv`` giving ``obs`` (``"state"``: a vector for
    ``MlpPolicy``; ``"rgbd"``: ``{"image", "state"}`` for ``MultiInputPolicy``), with ``reward_mode`` and
    ``control_mode`` passed to the task (default: its ``normalized_dense`` reward, the tool-frame action).
    ``seed``: the first reset's (env i gets ``seed + i`` on the CPU). ``backend``: ``"cpu"``, ``"gpu"`` or
    ``"auto"`` (the GPU when CUDA is there). ``learner_threads``: torch's threads in this process between CPU worker
    steps, while the workers wait (default 1 from state, the package's torch threads from the camera; one while the
    envs step: :class:`~maniskill_irb120.integrations.observations.StepThreads`)."""
    threads = learner_threads_for(obs, learner_threads)
    out = wrapped_vector_env(
        lambda venv: IRB120SB3VecEnv(venv, learner_threads=threads),
        env_id,
        num_envs,
        obs,
        backend=backend,
        reward_mode=reward_mode,
        control_mode=control_mode,
        wrappers=wrappers,
        env_kwargs=env_kwargs,
    )
    if seed is not None:
        out.seed(seed)
    return out


def make_sb3_env(
    env_id: str,
    obs: str = "state",
    *,
    reward_mode: Optional[str] = None,
    control_mode: Optional[str] = CONTROL_MODE,
    env_kwargs: Optional[dict] = None,
) -> gym.Env:
    """One CPU env with the same observation as :func:`make_sb3_vec_env`'s: what SB3's ``check_env`` checks, and
    what a trained model's ``predict`` is evaluated on."""
    return make_single_env(env_id, obs, reward_mode=reward_mode, control_mode=control_mode, env_kwargs=env_kwargs)


def deterministic_action(model: Any, obs: Any, norm: Any = None) -> np.ndarray:
    """``model``'s deterministic action for one observation, normalised as training normalises it (``VecNormalize``:
    the statistics as training left them, since ``normalize_obs`` updates nothing). ``norm`` is for a model loaded
    without its envs, whose statistics were saved beside it; by default the model's own ``VecNormalize``, if any."""
    norm = model.get_vec_normalize_env() if norm is None else norm
    return model.predict(obs if norm is None else norm.normalize_obs(obs), deterministic=True)[0]


class ProgressCallback(BaseCallback):
    """SB3's ``learn(callback=...)`` showing the run while it happens (``integrations.progress`` says why lines):
    every ``every_s`` seconds the env steps, their rate, the time left and the training episodes' success (SB3's
    ``ep_success_buffer``, the adapter's ``is_success``), with the random warm-up named while an off-policy learner is
    still before ``learning_starts``; every ``eval_every`` env steps (0: never) the deterministic policy on
    ``eval_episodes`` held-out seeds, logged as ``eval/held_out_success`` beside SB3's ``rollout/success_rate``.
    Between a rollout's end and the next one's start (the update, when no env steps) a :class:`Heartbeat` keeps
    the lines coming.
    ``held`` keeps each check as ``(env steps, successes, episodes)``; :meth:`check` runs one more (the end's)."""

    def __init__(
        self,
        total: int,
        env_id: str,
        obs: str,
        *,
        label: str = "sb3",
        eval_every: int = 0,
        eval_episodes: int = 10,
        every_s: float = EVERY_S,
    ):
        super().__init__()
        self.total, self.env_id, self.obs, self.label = int(total), env_id, obs, label
        self.eval_every, self.eval_episodes, self.every_s = int(eval_every), int(eval_episodes), float(every_s)
        self.held: list[tuple[int, int, int]] = []
        self.progress: Optional[Progress] = None
        self._next_eval = self.eval_every
        self._update: Optional[Heartbeat] = None

    def _on_training_start(self) -> None:
        self.progress = Progress(self.label, self.total, self.every_s)
        self.progress.report(self.model.num_timesteps, "started")

    def _on_rollout_end(self) -> None:
        # SB3 trains between a rollout's end and the next one's start: no _on_step comes in between
        if self.progress is not None and self._update is None:
            self._update = Heartbeat(self.progress, self.model.num_timesteps, "updating the policy").__enter__()

    def _on_rollout_start(self) -> None:
        self._end_update()

    def _on_training_end(self) -> None:
        self._end_update()

    def _end_update(self) -> None:
        if self._update is not None:
            self._update.__exit__(None, None, None)
            self._update = None

    def _on_step(self) -> bool:
        steps = self.model.num_timesteps
        # none at the budget's end: the caller's last check (check()) is the end's
        if self.eval_every and self.eval_episodes and self._next_eval <= steps < self.total:
            self._next_eval += self.eval_every * (1 + (steps - self._next_eval) // self.eval_every)
            self.check()
        self.progress.tick(steps, self.note)
        return True

    def note(self) -> str:
        """The state of learning in a few words: warm-up, training success, the last held-out check."""
        parts = []
        starts = getattr(self.model, "learning_starts", 0)
        if self.model.num_timesteps < starts:
            parts.append(f"random actions until learning_starts={starts:,}")
        buf = self.model.ep_success_buffer
        if buf:
            parts.append(f"training success {np.mean(buf):.2f} (last {len(buf)} episodes)")
        if self.held:
            steps, wins, n = self.held[-1]
            parts.append(f"held out {wins}/{n} at {steps:,}")
        return "; ".join(parts)

    def act(self, obs: Any) -> np.ndarray:
        return deterministic_action(self.model, obs)

    def check(self) -> tuple[int, int, int]:
        """The deterministic policy on ``eval_episodes`` held-out seeds now: printed, logged and kept in ``held``."""
        steps, n = self.model.num_timesteps, self.eval_episodes
        started = time.perf_counter()
        wins = held_out_success(self.act, self.env_id, self.obs, n)
        self.held.append((steps, wins, n))
        self.model.logger.record("eval/held_out_success", wins / n)
        took = time.perf_counter() - started
        line = f"held-out success {wins}/{n} (deterministic, seeds {HELD_OUT_SEED}..; {took:.0f} s)"
        if self.progress is not None:
            self.progress.report(steps, line)
        else:
            print(f"[{self.label}] {steps:,} env steps | {line}", flush=True)
        return self.held[-1]


class SelectOnValidation(ValidationSelection, BaseCallback):
    """Checkpoint selection for SB3 (``integrations.selection`` says why and how), from code or from an rl-zoo3
    hyperparams file's ``callback:`` list: every ``every`` env steps the deterministic policy plays ``episodes``
    validation episodes, and the best so far by success is kept in ``save_path`` as ``best_model.zip`` with its
    ``vecnormalize.pkl`` and ``best.json``. Not SB3's ``EvalCallback``: it keeps the best mean reward, which on these
    tasks prefers holding the object to succeeding."""

    def __init__(
        self,
        every: int,
        episodes: int = 30,
        save_path: str = "best_on_validation",
        seed: int = VALIDATION_SEED,
        env_id: Optional[str] = None,
        obs: Optional[str] = None,
        verbose: int = 1,
    ):
        BaseCallback.__init__(self, verbose)
        ValidationSelection.__init__(self, every, episodes, save_path, seed, verbose)
        self.env_id, self.obs = env_id, obs

    def _on_training_start(self) -> None:
        if self.env_id is None:  # the training env's own task: make_sb3_vec_env's envs carry their spec
            self.env_id = self.training_env.get_attr("spec", [0])[0].id.split(":")[-1]
        if self.obs is None:
            self.obs = "rgbd" if isinstance(self.training_env.observation_space, gym.spaces.Dict) else "state"
        self.start(self.model.num_timesteps)

    def act(self, obs: Any) -> np.ndarray:
        return deterministic_action(self.model, obs)

    def _on_step(self) -> bool:
        if self.due(self.num_timesteps):
            self.check()
        return True

    def _save(self, folder: Path) -> None:
        self.model.save(folder / "best_model.zip")
        norm = self.model.get_vec_normalize_env()
        if norm is not None:
            norm.save(str(folder / "vecnormalize.pkl"))

    def check(self) -> dict:
        """The deterministic policy on the validation episodes now, logged as ``eval/validation_success`` and kept
        where it is the best so far; returns the best."""
        rate, _ = self.validate(self.num_timesteps, self.act, self.env_id, self.obs, self._save)
        self.logger.record("eval/validation_success", rate)
        return self.best
