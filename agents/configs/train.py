"""Train one of ``agents/configs``' configs as its library's users would: rl-zoo3's flags for SB3, the runner for skrl.

rl-zoo3 (``python -m rl_zoo3.train --algo sac --env ID --gym-packages maniskill_irb120 -conf FILE``) does not install
beside this stack (its moviepy pins pillow < 12), and its env builder would hand SB3 ``gym.make`` envs where these
tasks need the CPU worker vector env; so this takes rl-zoo3's flags and file format and builds the env with
``make_sb3_vec_env``. ``--library skrl`` runs an ``skrl/<algo>_<task>.yaml`` through skrl's ``Runner``, as Isaac Lab's
skrl train script does.

    python -m agents.configs.train --algo sac --env GraspLift-IRB120-v1 -conf agents/configs/sb3/sac.yml
    python -m agents.configs.train --algo ppo --env GraspLift-IRB120-v1 -conf agents/configs/sb3/ppo_rgbd.yml \
        --env-kwargs obs_mode:rgbd
    python -m agents.configs.train --library skrl --algo ppo --env GraspLift-IRB120-v1

The observation is an env keyword, as rl-zoo3 passes one (``--env-kwargs obs_mode:rgbd``; ``state`` by default): a
camera config's ``MultiInputPolicy`` needs it, and a state config's ``MlpPolicy`` refuses it.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path
from typing import Optional

from agents.configs import loader
from maniskill_irb120.integrations.observations import OBS_KINDS


def parse(argv: Optional[list[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--library", choices=("sb3", "skrl"), default="sb3")
    p.add_argument("--algo", required=True, help="sb3: ppo, sac, td3, ddpg, tqc; skrl: ppo, sac")
    p.add_argument("--env", required=True, help="GraspLift-IRB120-v1 or TableClearing-IRB120-v1")
    p.add_argument("-conf", "--conf-file", type=Path, default=None, help="default: agents/configs/<library>/...")
    p.add_argument("-n", "--n-timesteps", type=int, default=-1, help="env steps (default: the config's)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("-f", "--log-folder", type=Path, default=Path("runs/configs"))
    p.add_argument("--backend", default="cpu", help="cpu, gpu or auto (make_vec_env's)")
    p.add_argument("--gym-packages", nargs="*", default=[], help="accepted for rl-zoo3's command line; unused")
    p.add_argument("--env-kwargs", nargs="+", default=[], metavar="KEY:VALUE",
                   help="the env's keywords, as rl-zoo3's (a value is a Python literal, or a word as a string); "
                   "obs_mode: state (default) or rgbd, the camera's image and state")  # fmt: skip
    a = p.parse_args(argv)
    try:
        a.env_kwargs = env_kwargs_of(a.env_kwargs)
    except ValueError as e:
        p.error(str(e))
    a.obs = obs = a.env_kwargs.get("obs_mode", "state")
    if obs not in OBS_KINDS:
        p.error(f"--env-kwargs obs_mode:{obs}: unknown; use one of {', '.join(OBS_KINDS)}")
    if a.library == "skrl" and obs != "state":
        p.error("--env-kwargs obs_mode:rgbd: the skrl configs are for state observations")
    a.sb3_config = None  # the entry train_sb3 builds, read once here to check it against the observation
    if a.library == "sb3":
        try:
            a.sb3_config = loader.sb3_config(a.algo, a.env, a.conf_file, obs)
        except (ValueError, KeyError, OSError) as e:
            p.error(str(e))
        policy = a.sb3_config.policy
        if (policy == "MultiInputPolicy") != (obs == "rgbd"):
            p.error(f"the config's {policy} and obs_mode {obs} disagree: a MultiInputPolicy config reads the camera "
                    "(--env-kwargs obs_mode:rgbd), an MlpPolicy config the state")  # fmt: skip
    return a


def env_kwargs_of(items: list[str]) -> dict:
    """rl-zoo3's ``--env-kwargs key:value ...`` as a dict: a value is read as a Python literal (``0.5``, ``True``,
    ``'rgbd'``), and a bare word that is none (``rgbd``) as that string."""
    out = {}
    for item in items:
        key, sep, text = item.partition(":")
        if not sep or not key:
            raise ValueError(f"--env-kwargs {item!r}: give KEY:VALUE, e.g. obs_mode:rgbd")
        try:
            out[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            if not text.isidentifier():
                raise ValueError(f"--env-kwargs {item!r}: {text!r} is neither a Python literal nor a word") from None
            out[key] = text
    return out


def train_sb3(a: argparse.Namespace) -> Path:
    from stable_baselines3.common.vec_env import VecNormalize

    cfg = a.sb3_config
    env_kwargs = {k: v for k, v in a.env_kwargs.items() if k != "obs_mode"}  # the observation is a.obs
    venv = cfg.vec_env(a.env, obs=a.obs, backend=a.backend, seed=a.seed, env_kwargs=env_kwargs or None)
    out = a.log_folder / a.algo / f"{a.env}_{a.seed}"
    try:
        model = loader.sb3_class(a.algo)(cfg.policy, venv, seed=a.seed, verbose=1, tensorboard_log=str(out),
                                         **cfg.model_kwargs(venv.action_space.shape[0]))  # fmt: skip
        callbacks = cfg.make_callbacks(out / "best")  # a selected checkpoint: out/best/best_model.zip
        model.learn(total_timesteps=cfg.n_timesteps if a.n_timesteps < 0 else a.n_timesteps, callback=callbacks)
        out.mkdir(parents=True, exist_ok=True)
        model.save(out / f"{a.env}.zip")  # rl-zoo3's layout: the model and, beside it, the normaliser
        if isinstance(venv, VecNormalize):
            venv.save(str(out / "vecnormalize.pkl"))
    finally:
        venv.close()
    return out


def train_skrl(a: argparse.Namespace) -> Path:
    from maniskill_irb120.integrations.skrl import make_runner, make_skrl_env

    cfg = loader.skrl_config(a.algo, a.env, a.conf_file)
    num_envs, wrappers = loader.skrl_env_settings(cfg)
    env_kwargs = {k: v for k, v in a.env_kwargs.items() if k != "obs_mode"}  # state only (parse says so)
    env = make_skrl_env(a.env, num_envs, "state", backend=a.backend, seed=a.seed, wrappers=wrappers,
                        env_kwargs=env_kwargs or None)  # fmt: skip
    out = a.log_folder / f"skrl_{a.algo}"
    run = loader.skrl_runner_config(cfg)
    run["seed"] = a.seed
    run["agent"] = dict(run["agent"], experiment=dict(directory=str(out), experiment_name=f"{a.env}_{a.seed}"))
    run["trainer"] = dict(run["trainer"], headless=True, close_environment_at_exit=False)  # closed below, once
    if a.n_timesteps > 0:  # skrl counts vector steps
        run["trainer"]["timesteps"] = max(1, a.n_timesteps // num_envs)
    try:
        runner = make_runner(env, run)
        # the config's hooks, e.g. a selected checkpoint: out/best/best_agent.pt (as the SB3 side's best_model.zip)
        for hook in loader.skrl_callbacks(cfg, out / "best"):
            hook.attach(runner.agent, env, a.env)
        runner.run("train")
    finally:
        env.close()
    return out


def main(argv: Optional[list[str]] = None) -> Path:
    a = parse(argv)
    out = train_sb3(a) if a.library == "sb3" else train_skrl(a)
    print(f"[configs] {a.library} {a.algo} on {a.env}: saved under {out}", flush=True)
    return out


if __name__ == "__main__":
    main()
