"""Read ``agents/configs``' files into what each library constructs: SB3 model keywords and env settings from
rl-zoo3's hyperparams format, skrl runner configs from Isaac Lab's YAML form.

Only the rl-zoo3 keys the configs use are understood (``policy``, ``n_timesteps``, ``n_envs``, ``normalize``,
``env_wrapper``, ``callback``, ``noise_type``/``noise_std``, ``policy_kwargs`` as a string); an unknown special key
would reach the model's constructor and fail there, so a config cannot silently mean less here than in rl-zoo3.
"""

from __future__ import annotations

import ast
import functools
import importlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

CONFIGS = Path(__file__).resolve().parent
SB3_ALGOS = ("ppo", "sac", "td3", "ddpg", "tqc")
SKRL_ALGOS = ("ppo", "sac")
ZOO_KEYS = ("policy", "n_timesteps", "n_envs", "normalize", "env_wrapper", "callback", "noise_type", "noise_std")
"""rl-zoo3's keys that are not the model's keyword arguments"""


SB3_CAMERA_ALGOS = ("ppo",)
"""the algorithms with a camera file, ``sb3/<algo>_rgbd.yml``"""


def sb3_path(algo: str, obs: str = "state") -> Path:
    """``sb3/<algo>.yml`` from state; from the camera (``obs="rgbd"``) ``sb3/<algo>_rgbd.yml``: rl-zoo3 keys an
    entry by env id alone, and the camera's entry (``MultiInputPolicy``, the image left unnormalised) is for the same
    env ids as the state's."""
    from maniskill_irb120.integrations.observations import check_obs

    if check_obs(obs) == "state":
        return CONFIGS / "sb3" / f"{algo}.yml"
    if algo not in SB3_CAMERA_ALGOS:
        raise ValueError(
            f"no camera config for SB3 {algo}: agents/configs/sb3 has one for {', '.join(SB3_CAMERA_ALGOS)} only"
        )
    return CONFIGS / "sb3" / f"{algo}_rgbd.yml"


def skrl_path(algo: str, env_id: str) -> Path:
    """``skrl/<algo>_<task>.yaml``; ``<algo>-defaults``: ``skrl/<algo>_defaults.yaml`` (either task)."""
    if algo.endswith("-defaults"):
        return CONFIGS / "skrl" / f"{algo.removesuffix('-defaults')}_defaults.yaml"
    return CONFIGS / "skrl" / f"{algo}_{env_id.split('-')[0].lower()}.yaml"


def sb3_class(algo: str) -> type:
    """The SB3 (or sb3-contrib) class of ``algo``."""
    if algo == "tqc":
        from sb3_contrib import TQC

        return TQC
    import stable_baselines3 as sb3

    return {"ppo": sb3.PPO, "sac": sb3.SAC, "td3": sb3.TD3, "ddpg": sb3.DDPG}[algo]


def wrappers_of(entries: Optional[list]) -> list[Callable]:
    """rl-zoo3's ``env_wrapper`` (or ``callback``) list (``[{"module.Class": {kwargs}}]`` or ``["module.Class"]``)
    as picklable constructors, innermost first."""
    out = []
    for entry in entries or []:
        name, kwargs = (entry, {}) if isinstance(entry, str) else next(iter(entry.items()))
        module, _, cls = name.rpartition(".")
        out.append(functools.partial(getattr(importlib.import_module(module), cls), **(kwargs or {})))
    return out


@dataclass
class SB3Config:
    """One env id's entry of an ``sb3/<algo>.yml``, taken apart."""

    algo: str
    policy: str
    n_envs: int
    n_timesteps: int
    normalize: Optional[dict]
    """VecNormalize's keywords (None: no VecNormalize)"""
    wrappers: list[Callable] = field(default_factory=list)
    kwargs: dict = field(default_factory=dict)
    """the model's keyword arguments (action noise still a spec: :meth:`model_kwargs` builds it)"""
    noise: Optional[tuple[str, float]] = None
    callbacks: list[Callable] = field(default_factory=list)
    """rl-zoo3's ``callback`` list as constructors (e.g. ``SelectOnValidation``'s checkpoint selection)"""

    def make_callbacks(self, save_dir: Optional[Path] = None) -> list:
        """The entry's callbacks (:func:`make_callbacks`)."""
        return make_callbacks(self.callbacks, save_dir)

    def vec_env(self, env_id: str, num_envs: Optional[int] = None, obs: str = "state", **kwargs):
        """The SB3 vector env this entry trains on: ``n_envs`` envs (or ``num_envs``) with its wrappers, under its
        VecNormalize where it names one; ``kwargs`` go to ``make_sb3_vec_env`` (backend, seed, reward_mode)."""
        from stable_baselines3.common.vec_env import VecNormalize

        from maniskill_irb120.integrations.sb3 import make_sb3_vec_env

        n = self.n_envs if num_envs is None else num_envs
        venv = make_sb3_vec_env(env_id, n, obs, wrappers=self.wrappers, **kwargs)
        return venv if self.normalize is None else VecNormalize(venv, **self.normalize)

    def model_kwargs(self, n_actions: int) -> dict:
        import numpy as np

        kwargs = dict(self.kwargs)
        if self.noise is not None:
            from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

            kind, std = self.noise
            cls = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}[kind]
            kwargs["action_noise"] = cls(np.zeros(n_actions), std * np.ones(n_actions))
        return kwargs


def policy_kwargs_of(text: str) -> dict:
    """rl-zoo3's ``policy_kwargs`` string (``"dict(net_arch=[...], activation_fn=nn.Tanh)"``), evaluated with
    ``dict`` and ``nn`` (torch.nn) only, as rl-zoo3 evaluates it."""
    import torch.nn as nn

    ast.parse(text, mode="eval")  # a syntax error names the config's text
    return eval(text, {"__builtins__": {}}, {"dict": dict, "nn": nn})  # noqa: S307 - a file of this repository


def sb3_config(algo: str, env_id: str, path: Optional[Path] = None, obs: str = "state") -> SB3Config:
    """``env_id``'s entry of ``path`` (default: :func:`sb3_path` of ``algo`` and ``obs``)."""
    path = path or sb3_path(algo, obs)
    entries = yaml.safe_load(path.read_text())
    if env_id not in entries:
        raise ValueError(f"{path} has no entry for {env_id}; it has {', '.join(entries)}")
    hp = dict(entries[env_id])
    normalize = hp.pop("normalize", False)
    if isinstance(normalize, str):
        normalize = ast.literal_eval(normalize)
    normalize = (dict(normalize) if isinstance(normalize, dict) else {}) if normalize else None
    noise_type, noise_std = hp.pop("noise_type", None), hp.pop("noise_std", None)
    if "policy_kwargs" in hp:
        hp["policy_kwargs"] = policy_kwargs_of(hp["policy_kwargs"])
    return SB3Config(
        algo=algo,
        policy=hp.pop("policy"),
        n_envs=int(hp.pop("n_envs", 1)),
        n_timesteps=int(float(hp.pop("n_timesteps"))),
        normalize=normalize,
        wrappers=wrappers_of(hp.pop("env_wrapper", None)),
        callbacks=wrappers_of(hp.pop("callback", None)),
        kwargs=hp,
        noise=None if noise_type is None else (noise_type, float(noise_std)),
    )


def skrl_config(algo: str, env_id: str, path: Optional[Path] = None) -> dict[str, Any]:
    """An ``skrl/<algo>_<task>.yaml`` as read, with the project's sections (``env``, ``callback``) left in for
    :func:`skrl_env_settings` and :func:`skrl_callbacks`; :func:`skrl_runner_config` is what skrl's ``Runner``
    takes."""
    return yaml.safe_load((path or skrl_path(algo, env_id)).read_text())


def make_callbacks(constructors: list[Callable], save_dir: Optional[Path] = None) -> list:
    """``callback`` constructors (:func:`wrappers_of`'s) called, each one that keeps files (a ``save_path``) keeping
    them in ``save_dir`` where given (a run's own folder, as rl-zoo3 puts its best model in the run's log folder)."""
    out = []
    for make in constructors:
        if save_dir is not None and "save_path" in inspect.signature(make.func).parameters:
            make = functools.partial(make, save_path=str(save_dir))
        out.append(make())
    return out


SKRL_PROJECT_KEYS = ("env", "callback")
"""the sections of the project's skrl YAML that skrl's runner does not read: the env's settings and the hooks"""


def skrl_runner_config(cfg: dict) -> dict[str, Any]:
    """``cfg`` without :data:`SKRL_PROJECT_KEYS`, what ``skrl.utils.runner.torch.Runner`` takes."""
    return {k: v for k, v in cfg.items() if k not in SKRL_PROJECT_KEYS}


def skrl_callbacks(cfg: dict, save_dir: Optional[Path] = None) -> list:
    """The ``callback`` section (rl-zoo3's ``callback`` form), built: e.g.
    ``maniskill_irb120.integrations.skrl.SelectOnValidation``, each to be ``attach``-ed to the agent before training,
    keeping its files in ``save_dir`` where given."""
    return make_callbacks(wrappers_of(cfg.get("callback")), save_dir)


def skrl_env_settings(cfg: dict) -> tuple[int, list[Callable]]:
    """The ``env`` section: the number of envs and the env wrappers (rl-zoo3's ``env_wrapper`` form)."""
    env = cfg.get("env", {})
    return int(env.get("num_envs", 4)), wrappers_of(env.get("wrappers"))
