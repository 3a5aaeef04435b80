"""The observation other RL libraries get, and the envs that give it (one CPU env, or a batch on either backend).

Libraries with generic policies read a flat observation: Stable-Baselines3's ``MultiInputPolicy`` raises
``NotImplementedError: Nested observation spaces are not supported`` on the task's ``rgbd`` observation, whose
``agent``, ``extra``, ``sensor_param`` and ``sensor_data`` are dicts. So:

- ``obs="state"``: the task's ``obs_mode="state"`` vector, ``(D,)`` float32 (SB3's ``MlpPolicy``).
- ``obs="rgbd"``: a flat Dict of ``"image"``, ``(4, 84, 84)`` uint8, channel-first, and ``"state"``, ``(D,)``
  float32: the proprioception and extras (``agent/*``, ``extra/*``) that ManiSkill's
  ``FlattenRGBDObservationWrapper`` flattens. The camera parameters are left out (a fixed camera: the same
  numbers every step).

Why the image is one uint8 ``RGB + depth`` array, channel first: SB3 routes a key to its CNN (``NatureCNN``) only
when ``is_image_space`` holds (a 3-D uint8 Box bounded by 0 and 255) and, channel-first, uses it as it is; any
other key it flattens into the MLP input, so a separate ``(84, 84, 1)`` depth key would reach the policy as 7 056
unstructured inputs. Depth is the hand camera's int16 millimetres at :data:`DEPTH_MM_PER_LEVEL` mm per level, so
the 255 levels cover 0-510 mm: from the rest pose the camera sees the tray floor at about 280 mm, an object top at
10-30 mm; farther saturates at 255. The CNN divides all four channels by 255 as it does any image.

The conversion runs where the env is stepped (in each CPU worker, or on the GPU for the whole batch), as ManiSkill
observation wrappers: :func:`observation_wrappers`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, Optional

import gymnasium as gym
import torch

from maniskill_irb120.errors import UsageError

OBS_KINDS = ("state", "rgbd")
"""what an adapter can give a library: the state vector, or the hand camera's image plus a state vector"""
DEPTH_MM_PER_LEVEL = 2
"""millimetres of depth per uint8 level in the image's fourth channel (0-510 mm)"""
IMAGE_KEY = "image"
STATE_KEY = "state"
CONTROL_MODE = "pd_ee_delta_tool"
"""the original report's tool-frame action (the tasks' other control modes pass through ``control_mode``)"""


def check_obs(obs: str) -> str:
    if obs not in OBS_KINDS:
        raise UsageError(f"unknown obs {obs!r}; use one of {OBS_KINDS} (the state vector, or image + state)")
    return obs


class ImageStateObservation(gym.ObservationWrapper):
    """On ManiSkill's ``FlattenRGBDObservationWrapper`` output (``rgb``, ``depth``, ``state``, batched torch): the
    ``{"image": (N, 4, H, W) uint8, "state": (N, D) float32}`` observation of the module doc. Batched and on the
    env's device, so on ``physx_cuda`` the whole batch converts on the GPU."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        base = env.unwrapped
        have = set(base._init_raw_obs) if isinstance(base._init_raw_obs, dict) else set()
        if not {"rgb", "depth", "state"} <= have:
            raise ValueError(
                "ImageStateObservation needs obs_mode='rgbd' flattened by ManiSkill's FlattenRGBDObservationWrapper "
                f"(keys rgb, depth, state); the observation has {sorted(have) or type(base._init_raw_obs).__name__}"
            )
        base.update_obs_space(self.observation(base._init_raw_obs))

    def observation(self, obs: dict) -> dict[str, torch.Tensor]:
        return image_state(obs)


def image_state(obs: dict) -> dict[str, torch.Tensor]:
    """``FlattenRGBDObservationWrapper``'s batched ``rgb``/``depth``/``state`` -> ``{"image", "state"}`` (module doc):
    what :class:`ImageStateObservation` gives, for code that reads the flattened observation itself (an evaluation
    loop that was written for the project's own policies)."""
    depth = obs["depth"].to(torch.int32).clamp(0, 255 * DEPTH_MM_PER_LEVEL)
    depth = torch.div(depth + DEPTH_MM_PER_LEVEL // 2, DEPTH_MM_PER_LEVEL, rounding_mode="floor").clamp(max=255)
    image = torch.cat([obs["rgb"], depth.to(torch.uint8)], dim=-1).permute(0, 3, 1, 2).contiguous()
    return {IMAGE_KEY: image, STATE_KEY: obs[STATE_KEY].float()}


def observation_wrappers(obs: str) -> list[Callable[[gym.Env], gym.Env]]:
    """The ManiSkill observation wrappers, innermost first, that turn the task's ``obs_mode`` output into ``obs``'s
    observation (none for ``"state"``: ManiSkill's flat state vector already is one)."""
    if check_obs(obs) == "state":
        return []
    from mani_skill.utils.wrappers.flatten import FlattenRGBDObservationWrapper

    return [FlattenRGBDObservationWrapper, ImageStateObservation]


def env_kwargs_for(
    obs: str, reward_mode: Optional[str], control_mode: Optional[str], env_kwargs: Optional[dict]
) -> dict:
    """``gym.make`` keyword arguments for ``obs``: the obs mode, the reward and control modes as given (the task
    refuses unknown ones by name), and no renderer at all for state (nothing is drawn)."""
    kwargs = dict(env_kwargs or {})
    for name in ("obs_mode", "num_envs", "sim_backend"):
        if name in kwargs:
            raise ValueError(f"env_kwargs may not set {name!r}: the adapter's obs, num_envs and backend choose it")
    kwargs.update(obs_mode=check_obs(obs), control_mode=control_mode or CONTROL_MODE)
    if reward_mode is not None:
        kwargs["reward_mode"] = reward_mode
    if obs == "state":
        kwargs.setdefault("render_backend", "none")
    return kwargs


def make_single_env(
    env_id: str,
    obs: str = "state",
    *,
    reward_mode: Optional[str] = None,
    control_mode: Optional[str] = CONTROL_MODE,
    wrappers: Sequence[Callable[[gym.Env], gym.Env]] = (),
    env_kwargs: Optional[dict] = None,
) -> gym.Env:
    """One CPU env with numpy observations, actions and scalars (ManiSkill's ``CPUGymWrapper``) giving ``obs``'s
    observation: what a library's single-env checker (SB3's ``check_env``) takes, and what a held-out evaluation
    steps. ``wrappers`` go on the ManiSkill env before the observation wrappers (e.g. an action wrapper)."""
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    import maniskill_irb120  # noqa: F401  (registers the tasks)

    env = gym.make(env_id, num_envs=1, **env_kwargs_for(obs, reward_mode, control_mode, env_kwargs))
    for w in [*wrappers, *observation_wrappers(obs)]:
        env = w(env)
    return CPUGymWrapper(env)


def make_vector_env(
    env_id: str,
    num_envs: int,
    obs: str = "state",
    *,
    backend: str = "auto",
    reward_mode: Optional[str] = None,
    control_mode: Optional[str] = CONTROL_MODE,
    wrappers: Sequence[Callable[[gym.Env], gym.Env]] = (),
    env_kwargs: Optional[dict] = None,
) -> gym.vector.VectorEnv:
    """``num_envs`` envs giving ``obs``'s observation as batched torch tensors, auto-reset with
    ``final_observation``/``final_info`` (:func:`maniskill_irb120.vector.make_vec_env`: ``backend="cpu"`` runs them
    in worker processes, ``"gpu"`` batches them on ``physx_cuda``, ``"auto"`` picks the GPU when CUDA is there).

    With CPU workers this process is set to one torch thread, as the project's own trainers are
    (``agents/common/envs.py``); the adapters then hand the learner its threads between steps (:class:`StepThreads`)."""
    from maniskill_irb120.vector import CPUVectorEnv, make_vec_env

    if backend == "inprocess":
        raise ValueError("backend='inprocess' is one env without batching; use make_single_env, or 'cpu'/'gpu'")
    kwargs = env_kwargs_for(obs, reward_mode, control_mode, env_kwargs)
    env = make_vec_env(
        env_id,
        num_envs,
        backend=backend,
        wrappers=[*wrappers, *observation_wrappers(obs)],
        record_metrics=True,
        **kwargs,
    )
    if isinstance(env, CPUVectorEnv):
        torch.set_num_threads(1)
    return env


class StepThreads:
    """torch's intra-op threads in this process around a CPU worker env's steps: one while the envs step, ``learner``
    between steps. Nothing changes on the GPU backend.

    Why one while stepping: env 0 steps in this process beside the worker processes, and each of its many small torch
    ops would wait at its join for a second thread that a worker holds the core of (SB3's SAC from state on 2 cores:
    ~170 ms a step with 2 threads throughout, ~7 ms with 1). Why ``learner`` between steps: the workers sleep then,
    waiting for actions, while the learner acts and updates. A CNN learner gains from the cores (2 cores, 4 envs,
    GraspLift camera: SB3 PPO 45 -> 62 env steps/s, SAC 2.4 -> 4.0), a small MLP's ops lose to the hand-offs (state:
    PPO 333 -> 249, SAC 103 -> 115), hence :func:`learner_threads_for`' default (docs/rl_libraries.md)."""

    def __init__(self, env: gym.vector.VectorEnv, learner: int):
        from maniskill_irb120.vector import CPUVectorEnv

        self.active = isinstance(env, CPUVectorEnv)
        self.learner = check_learner_threads(learner)
        if self.active:
            torch.set_num_threads(learner)

    @contextmanager
    def stepping(self) -> Iterator[None]:
        """One torch thread inside, ``learner`` after (on CPU workers)."""
        if not self.active:
            yield
            return
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(self.learner)


def check_learner_threads(threads: int) -> int:
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"learner_threads must be an int >= 1, got {threads!r}")
    return threads


def learner_threads_for(obs: str, threads: Optional[int] = None) -> int:
    """``threads`` if given, else the default of :class:`StepThreads`' ``learner`` for ``obs``: 1 from state (an MLP),
    :data:`maniskill_irb120.vector.TORCH_THREADS` from the camera (a CNN)."""
    from maniskill_irb120.vector import TORCH_THREADS

    if threads is not None:
        return check_learner_threads(threads)
    return TORCH_THREADS if check_obs(obs) == "rgbd" else 1


def wrapped_vector_env(wrap: Callable[[gym.vector.VectorEnv], Any], env_id: str, num_envs: int, obs: str, **kwargs):
    """``wrap`` (a library's adapter) around :func:`make_vector_env`'s envs (``kwargs``: its keywords); the envs are
    closed again, worker processes and all, if the adapter refuses them."""
    if num_envs < 1:
        raise UsageError(f"num_envs must be >= 1, got {num_envs}")
    venv = make_vector_env(env_id, num_envs, obs, **kwargs)
    try:
        return wrap(venv)
    except BaseException:
        venv.close()
        raise
