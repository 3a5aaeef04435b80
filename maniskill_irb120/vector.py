"""One vector-env interface for GPU-batched and CPU process-parallel simulation.

ManiSkill batches envs inside one process only on ``physx_cuda``. On a CPU-only machine the same
training code gets N ``CPUGymWrapper`` envs, env 0 in this process and the others in worker processes
(gymnasium ``AsyncVectorEnv``, shared memory, same-step autoreset), behind the exact interface of
``ManiSkillVectorEnv``: batched torch obs dicts, torch rewards/terminations, auto-reset with
``final_observation`` / ``final_info`` / ``_final_info``, partial resets via ``options={"env_idx": ...}`` and
optional ``episode`` metrics.

Why env 0 runs here: a step is synchronous, so while the workers step this process only waits, and while it
gathers their results they wait. Stepping env 0 in that wait fills it, and that env pays no pipe, pickling or
wake-up (docs/notes/sim-speed.md).
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch

from maniskill_irb120.envs import check_env_id
from maniskill_irb120.envs.contract import as_action_array, check_env_idx, check_finite_actions
from maniskill_irb120.errors import UsageError

TORCH_THREADS = torch.get_num_threads()
"""torch's intra-op threads when the package was imported, before a CPU worker env set this process to one: what a
learner that wants the cores back while the workers wait can use (``integrations.observations.StepThreads``)"""


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


def _make_single_env(env_id: str, env_kwargs: dict, wrappers: Sequence[Callable], ignore_terminations: bool) -> gym.Env:
    """One CPU env as a plain numpy gymnasium env (ManiSkill's ``CPUGymWrapper``): what each worker steps, and
    env 0 in the calling process."""
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import maniskill_irb120  # noqa: F401  (registers our envs in the worker)

    env = gym.make(env_id, num_envs=1, **env_kwargs)
    for w in wrappers:
        env = w(env)
    return CPUGymWrapper(env, ignore_terminations=ignore_terminations)


def _make_worker_env(
    env_id: str,
    env_kwargs: dict,
    wrappers: Sequence[Callable],
    ignore_terminations: bool,
    lp_num_threads: Optional[int],
) -> gym.Env:
    if multiprocessing.parent_process() is not None:
        # a worker: Ctrl-C in the terminal reaches the whole process group, and each worker would print its
        # KeyboardInterrupt's traceback (gymnasium's workers catch it and send it back, to be printed once more);
        # the parent, which got the same Ctrl-C, closes them. Not in the parent, where gymnasium calls this once to
        # read the spaces. The same for a SIGTERM to the group (a scheduler's, a session's end): the trainers take
        # it as a Ctrl-C (agents.common.args.entry). A worker whose parent is gone ends at its pipe's end.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # lavapipe reads this when the render device is created, i.e. inside gym.make below
    if lp_num_threads:
        os.environ.setdefault("LP_NUM_THREADS", str(lp_num_threads))
    # one worker per core: torch's intra-op threads would only spin against the other workers
    torch.set_num_threads(1)
    return _make_single_env(env_id, env_kwargs, wrappers, ignore_terminations)


def _same_step_autoreset(env: gym.Env, action: np.ndarray) -> tuple:
    """One step of a single env with gymnasium's same-step autoreset, exactly as its ``AsyncVectorEnv`` worker does
    it: an episode that ends is reset at once, and the info carries ``final_info`` and ``final_obs``."""
    obs, rew, term, trunc, info = env.step(action)
    if term or trunc:
        reset_obs, reset_info = env.reset()
        info = {"final_info": info, "final_obs": obs, **reset_info}
        obs = reset_obs
    return obs, rew, term, trunc, info


def _join_obs(first: Any, rest: Any = None) -> Any:
    """Env 0's unbatched observation in front of the workers' batch (``None``: no workers), as a new array: nothing
    aliases shared memory or the env's own buffers."""
    if isinstance(first, dict):
        return {k: _join_obs(first[k], None if rest is None else rest[k]) for k in first}
    first = np.asarray(first)[None]
    return first.copy() if rest is None else np.concatenate([first, rest])


def _rows(batch: Any, idx: int | slice) -> Any:
    """Rows ``idx`` of a (possibly nested) numpy batch: env 0's observation, or the workers'."""
    return {k: _rows(v, idx) for k, v in batch.items()} if isinstance(batch, dict) else batch[idx]


def _join_infos(infos: dict, rest: dict, n: int) -> dict:
    """The workers' batched infos (envs 1..n-1, with gymnasium's ``_key`` masks) placed into ``infos`` (n envs,
    env 0's already added by ``VectorEnv._add_info``): the layout gymnasium would have built for all n."""
    for key, value in rest.items():
        if isinstance(value, dict):
            infos[key] = _join_infos(infos.get(key, {}), value, n)
            continue
        value = np.asarray(value)
        if key not in infos:
            infos[key] = (
                np.full(n, None, dtype=object)
                if value.dtype == object
                else np.zeros((n, *value.shape[1:]), dtype=value.dtype)
            )
        infos[key][1:] = value
    return infos


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


class WorkerError(UsageError, RuntimeError):
    """An env raised an exception inside its worker process. gymnasium shuts that worker down for good and prints
    the worker's traceback (and the others', and one more line each); this says in one line which env raised what,
    and that the vector env must be made again. The worker's traceback stays in ``worker_traceback`` for whoever
    debugs the env. A UsageError, so a command line prints it as one line with exit status 2; raised as a subclass
    that is also the worker's exception type (an AttributeError from ``call`` is still caught as one)."""

    def __init__(self, message: str, env_index: int, worker_traceback: str):
        super().__init__(message)
        self.env_index, self.worker_traceback = env_index, worker_traceback

    def __str__(self) -> str:  # the message as given (KeyError's own str would quote it)
        return str(self.args[0])

    @classmethod
    def like(cls, exctype: type[BaseException]) -> type[WorkerError]:
        """A WorkerError that is an ``exctype`` too, so code catching the worker's exception type still does."""
        if issubclass(cls, exctype):
            return cls
        try:
            return type(cls.__name__, (cls, exctype), {"__module__": cls.__module__, "__doc__": cls.__doc__})
        except TypeError:  # an exception type that cannot be combined (a C layout): the WorkerError alone
            return cls


CLOSE_TIMEOUT_S = 30.0  # how long close() waits for a step in flight before it terminates the workers


def _interrupts_held(fn: Callable, *args, **kwargs) -> Any:
    """``fn(*args, **kwargs)`` with a Ctrl-C (or a SIGTERM taken as one) held until it returns, then delivered as
    usual.

    gymnasium's ``AsyncVectorEnv`` sends a command to each worker and only then records that replies are due (and
    clears that once it has read them). A KeyboardInterrupt between the two leaves a reply unread with nothing
    expecting it: ``close()`` then reads that reply as the answer to its own "close", shuts the pipe, and the worker,
    whose real answer meets a closed pipe, prints a BrokenPipeError traceback. Holding the signal over those calls,
    which last one worker step, keeps the two sides in step. A second Ctrl-C while one is held is delivered at once:
    whoever presses twice wants out now. Only the main thread receives signals, so other threads call ``fn`` as is.
    """
    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    # a Python handler of SIGINT or SIGTERM (errors.terminate_as_interrupt's) is held; one that is ignored, the
    # default, or set outside Python has nothing of ours to hold
    previous = {s: h for s in (signal.SIGINT, signal.SIGTERM) if callable(h := signal.getsignal(s))}
    if not previous:
        return fn(*args, **kwargs)
    held = []

    def put_back():
        for s, h in previous.items():
            if signal.getsignal(s) is hold:
                signal.signal(s, h)

    def hold(signum, frame):
        held.append(signum)
        if len(held) == 2:  # the second press
            put_back()
            signal.raise_signal(signum)

    for s in previous:
        signal.signal(s, hold)
    try:
        return fn(*args, **kwargs)
    finally:
        put_back()
        if len(held) == 1:
            signal.raise_signal(held[0])  # through the restored handler: KeyboardInterrupt by default


class CPUVectorEnv(gym.vector.VectorEnv):
    """N single-env ManiSkill envs, env 0 in this process (``local_first``) and the others in worker processes, with
    ManiSkillVectorEnv's batched torch interface.

    ``local_first`` (default: with two envs or more) steps env 0 here while the workers step theirs; a single env
    stays in a worker unless asked, since ``backend="cpu"`` with one env is a request for a separate process (and
    make_vec_env's ``"inprocess"`` backend is the one-env-here case)."""

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
        local_first: Optional[bool] = None,
        **env_kwargs,
    ):
        if num_envs < 1:
            raise UsageError(f"num_envs must be >= 1, got {num_envs}")
        if env_kwargs.get("sim_backend", "physx_cpu") not in ("physx_cpu", "cpu", "auto"):
            raise ValueError(f"CPUVectorEnv workers run physx_cpu, got sim_backend={env_kwargs['sim_backend']!r}")
        env_kwargs.pop("sim_backend", None)
        self.local_first = num_envs > 1 if local_first is None else bool(local_first)
        self._local: Optional[gym.Env] = None
        self._venv: Optional[gym.vector.AsyncVectorEnv] = None
        workers = num_envs - int(self.local_first)
        if workers:
            fn = functools.partial(
                _make_worker_env, env_id, env_kwargs, tuple(wrappers), ignore_terminations, lp_num_threads
            )
            # gymnasium builds one env in this process to read the spaces (AsyncVectorEnv's dummy env), i.e. runs
            # the worker's setup here too: without the restore, every trainer's learner was left on one torch thread
            threads, lp = torch.get_num_threads(), os.environ.get("LP_NUM_THREADS")
            try:
                self._venv = gym.vector.AsyncVectorEnv(
                    [fn] * workers,
                    context=context,
                    shared_memory=True,
                    # joined with env 0's observation into a new array each step: no copy of shared memory needed
                    copy=not self.local_first,
                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
                )
            except (EOFError, ConnectionError) as e:  # a worker died before it answered: its own stderr says why
                raise RuntimeError(
                    f"a CPU env worker process exited while starting ({type(e).__name__}); its message is above. "
                    'A script that makes the envs outside if __name__ == "__main__": has each worker run it again'
                ) from None
            finally:
                torch.set_num_threads(threads)
                if lp is None:
                    os.environ.pop("LP_NUM_THREADS", None)
                else:
                    os.environ["LP_NUM_THREADS"] = lp
        if self._venv is not None:
            # gymnasium's own error report, replaced for this env's workers (see WorkerError)
            self._venv._raise_if_errors = functools.partial(_raise_worker_errors, self._venv, int(self.local_first))
            for process in self._venv.processes:  # the workers ignore SIGTERM (_make_worker_env): where gymnasium's
                process.terminate = process.kill  # close terminates them, SIGKILL stops them
        if self.local_first:
            try:
                self._local = _make_single_env(env_id, env_kwargs, tuple(wrappers), ignore_terminations)
            except BaseException:
                if self._venv is not None:
                    self._venv.close()
                raise
            single_obs, single_act = self._local.observation_space, self._local.action_space
            metadata, self.render_mode = self._local.metadata, self._local.render_mode
        else:
            single_obs, single_act = self._venv.single_observation_space, self._venv.single_action_space
            metadata, self.render_mode = self._venv.metadata, self._venv.render_mode
        self.num_envs = num_envs
        self.ignore_terminations = ignore_terminations
        self.record_metrics = record_metrics
        self.single_observation_space = single_obs
        self.single_action_space = single_act
        self.observation_space = gym.vector.utils.batch_space(single_obs, num_envs)
        self.action_space = gym.vector.utils.batch_space(single_act, num_envs)
        self.metadata = dict(metadata, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        self.spec = None
        self.device = torch.device("cpu")
        self.success_once = torch.zeros(num_envs, dtype=torch.bool)
        self.fail_once = torch.zeros(num_envs, dtype=torch.bool)
        self.returns = torch.zeros(num_envs, dtype=torch.float32)
        self.elapsed_steps = torch.zeros(num_envs, dtype=torch.int32)
        self._last_obs: Any = None  # the numpy batch last returned: what a partial reset leaves in place

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: Optional[int | list[int]] = None, options: Optional[dict] = None):
        self._check_usable()
        options = dict(options or {})
        mask = np.ones(self.num_envs, dtype=bool)
        if "env_idx" in options:
            idx = check_env_idx(options.pop("env_idx"), self.num_envs)
            mask[:] = False
            mask[idx] = True
        if self._last_obs is None and not mask.all():
            raise RuntimeError(
                "reset(options={'env_idx': ...}) before a first full reset(): the other envs have no observation yet"
            )
        seeds = self._seeds(seed)
        if self._local is None:
            if not mask.all():
                options["reset_mask"] = mask
            obs, info = _interrupts_held(self._venv.reset, seed=seed, options=options or None)
        else:
            obs, info = self._reset_joined(seeds, mask, options)
        self._last_obs = obs
        m = torch.from_numpy(mask)
        self.success_once[m] = False
        self.fail_once[m] = False
        self.returns[m] = 0
        self.elapsed_steps[m] = 0
        return _to_torch(obs), _to_torch(_strip_masks(info))

    def _seeds(self, seed: Optional[int | list[int]]) -> list[Optional[int]]:
        """One seed per env, as gymnasium's vector envs spread them: ``s + i`` for env i."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(f"reset got {len(seeds)} seeds for {self.num_envs} envs")
        return seeds

    def _reset_joined(self, seeds: list, mask: np.ndarray, options: dict) -> tuple[Any, dict]:
        """reset() with env 0 here: each side resets what ``mask`` selects and keeps the rest's last observation."""
        info: dict = {}
        rest_obs, rest_info, rest_mask = None, {}, mask[1:]
        if self._venv is not None and rest_mask.any():
            rest_options = dict(options, reset_mask=rest_mask) if not rest_mask.all() else options
            rest_obs, rest_info = _interrupts_held(self._venv.reset, seed=seeds[1:], options=rest_options or None)
        elif self._venv is not None:
            rest_obs = _rows(self._last_obs, slice(1, None))
        if mask[0]:
            local_obs, local_info = self._local.reset(seed=seeds[0], options=options or None)
            info = self._add_info(info, local_info, 0)
        else:
            local_obs = _rows(self._last_obs, 0)
        return _join_obs(local_obs, rest_obs), _join_infos(info, rest_info, self.num_envs)

    def _step_all(self, actions: np.ndarray) -> tuple:
        """The numpy step of every env: the workers' launched first, env 0's stepped here while they run."""
        if self._local is None:
            return _interrupts_held(self._venv.step, actions)
        try:
            if self._venv is not None:
                _interrupts_held(self._venv.step_async, actions[1:])
            obs, rew, term, trunc, info = _same_step_autoreset(self._local, actions[0])
        except BaseException:
            # collect the workers' step, so the next call (close() included) finds them idle; a Ctrl-C held over
            # step_async arrives as it returns, with the step already in flight
            if self._venv is not None and self._venv._state is gym.vector.async_vector_env.AsyncState.WAITING_STEP:
                _interrupts_held(self._venv.step_wait)
            raise
        infos = self._add_info({}, info, 0)
        if self._venv is None:
            return _join_obs(obs), np.array([rew]), np.array([term]), np.array([trunc]), infos
        rest_obs, rest_rew, rest_term, rest_trunc, rest_info = _interrupts_held(self._venv.step_wait)
        return (
            _join_obs(obs, rest_obs),
            np.concatenate([[rew], rest_rew]),
            np.concatenate([[term], rest_term]),
            np.concatenate([[trunc], rest_trunc]),
            _join_infos(infos, rest_info, self.num_envs),
        )

    def step(self, actions):
        actions = self._checked_actions(actions)
        obs_np, rew, term, trunc, info_np = self._step_all(actions)
        self._last_obs = obs_np
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

    def call(self, name: str, *args, **kwargs) -> tuple:
        """Each env's attribute ``name`` (called with the arguments if it is a method), in env order."""
        self._check_usable()
        out = []
        if self._local is not None:
            if name in ("reset", "step", "close"):  # as gymnasium's workers refuse them
                raise ValueError(f"Trying to call function `{name}` with `call`, use `{name}` directly instead.")
            attr = self._local.get_wrapper_attr(name)
            out.append(attr(*args, **kwargs) if callable(attr) else attr)
        if self._venv is not None:
            out.extend(_interrupts_held(self._venv.call, name, *args, **kwargs))
        return tuple(out)

    def render(self):
        """Each env's ``render()``; checked here first, since a worker that raises is lost for good."""
        self._check_usable()
        if self.render_mode is None:
            raise RuntimeError(
                "render_mode is not set: pass render_mode='rgb_array' (or 'sensors', 'all') to make_vec_env"
            )
        return self.call("render")

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
            raise UsageError(
                f"actions have shape {actions.shape}, expected {self.action_space.shape} (one action per env); "
                "nothing was stepped"
            )
        check_finite_actions(actions)
        return actions

    def _check_usable(self) -> None:
        """RuntimeError after ``close()`` or once a worker died, instead of gymnasium's pipe errors."""
        if self.closed:
            raise RuntimeError("the vector env is closed; make a new one with make_vec_env(...)")
        first = int(self.local_first)
        pipes = self._venv.parent_pipes if self._venv is not None else []
        dead = [i + first for i, pipe in enumerate(pipes) if pipe is None]
        if dead:
            raise RuntimeError(
                f"worker(s) {dead} of this vector env were shut down after raising an error (the "
                "WorkerError raised then); close() it and make a new one with make_vec_env(...)"
            )

    def close_extras(self, **kwargs):
        """The workers closed, waiting at most ``timeout`` (default :data:`CLOSE_TIMEOUT_S`) for a step or reset
        still in flight, then terminated: a Ctrl-C that lands while gymnasium is collecting the workers' results
        leaves a half-read step, and gymnasium's own close (no timeout) would then wait for a reply that never
        comes. ``terminate=True`` stops them at once."""
        kwargs.setdefault("timeout", CLOSE_TIMEOUT_S)
        # getattr: not set when __init__ failed before the envs existed
        if getattr(self, "_venv", None) is not None:
            self._venv.close(**kwargs)
        if getattr(self, "_local", None) is not None:
            self._local.close()


def _raise_worker_errors(venv: gym.vector.AsyncVectorEnv, first: int, successes) -> None:
    """gymnasium's ``AsyncVectorEnv._raise_if_errors`` without its printing: each failed worker's pipe is closed
    (it is shut down, as gymnasium does) and the last error is raised as one :class:`WorkerError` naming the env
    (``first``: the env index of worker 0, 1 when env 0 runs in this process)."""
    if all(successes):
        return
    errors = [venv.error_queue.get() for _ in range(len(successes) - sum(successes))]
    for index, *_ in errors:
        venv.parent_pipes[index].close()
        venv.parent_pipes[index] = None
    venv._state = gym.vector.async_vector_env.AsyncState.DEFAULT
    index, exctype, value, trace = errors[-1]
    others = f" (and env(s) {[i + first for i, *_ in errors[:-1]]})" if len(errors) > 1 else ""
    raise WorkerError.like(exctype)(
        f"env {index + first}{others} raised {exctype.__name__} in its worker process: {value}; that worker is shut "
        "down, so close() this vector env and make a new one with make_vec_env(...) (the worker's traceback: the "
        "exception's worker_traceback)",
        index + first,
        trace,
    )


def _refuse_in_bootstrapping_worker() -> None:
    """A worker process that is still importing the parent's main script (``spawn``/``forkserver`` import it again)
    and reached a ``make_vec_env`` there: the script has no ``if __name__ == "__main__":`` guard, and the worker would
    start workers of its own. Python's RuntimeError says so in a traceback of some 30 lines, followed by the parent's
    own for the lost pipe; this says it in one line and ends the worker (the parent then reports a worker that
    exited while starting)."""
    import multiprocessing

    if getattr(multiprocessing.current_process(), "_inheriting", False):
        print(
            "make_vec_env(backend='cpu') was called while a worker process imported your script: put the code that "
            'makes the envs under if __name__ == "__main__": (the workers import the script again)',
            file=sys.stderr,
            flush=True,
        )
        raise SystemExit(2)


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
    ``"gpu"``, ``"cpu"`` (:class:`CPUVectorEnv`: env 0 in this process, the others in worker processes) or
    ``"inprocess"`` (one CPU env, num_envs must be 1).
    ``wrappers`` are applied to each ManiSkill env before batching (e.g. FlattenRGBDObservationWrapper).
    Seeding: ``reset(seed=s)`` seeds env i with ``s + i`` on CPU; the GPU env derives its own per-env
    seeds from ``s``, so the two backends draw different (equally distributed) initial states.
    """
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    check_env_id(env_id)
    if backend not in ("auto", "gpu", "cpu", "inprocess"):
        raise UsageError(f"unknown backend {backend!r}; use 'auto', 'gpu', 'cpu' or 'inprocess'")
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
            raise UsageError("backend='gpu' needs CUDA; none is available here (use backend='cpu')")
        env = gym.make(env_id, num_envs=num_envs, sim_backend="physx_cuda", **env_kwargs)
    elif backend == "inprocess":
        if num_envs != 1:
            raise ValueError("backend='inprocess' runs one CPU env; use backend='cpu' for num_envs > 1")
        env = gym.make(env_id, num_envs=1, sim_backend="physx_cpu", **env_kwargs)
    else:
        _refuse_in_bootstrapping_worker()
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
