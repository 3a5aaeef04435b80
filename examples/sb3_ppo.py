"""Stable-Baselines3's PPO on a task, from the reward alone, through maniskill_irb120.integrations.sb3 (needs the
sb3 extra).

    .venv/bin/python examples/sb3_ppo.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 200000
    .venv/bin/python examples/sb3_ppo.py --obs rgbd --n-steps 64 --total-timesteps 256 --eval-episodes 2   # a look

It trains with the project's tuned config in rl-zoo3's format, read by ``agents/configs/loader.py``: from state
``agents/configs/sb3/ppo.yml`` (4 envs, ``VecNormalize`` on the observations, the absorbing value on success), from
the camera ``agents/configs/sb3/ppo_rgbd.yml`` (the same, with SB3's NatureCNN on the image and only the state vector
normalised), each setting's reason beside it in the file. The configs' checkpoint selection is the benchmark's
(``benchmarks.algorithms``); this example keeps the last policy. ``--library-defaults`` takes SB3's PPO as it comes:
``n_steps=2048`` per env, batch 64, 10 epochs, gamma 0.99, lambda 0.95, on 2 envs.
SB3 bootstraps an episode cut at the step limit from the adapter's ``TimeLimit.truncated``.

A line every 10 s shows the env steps, their rate, the time left and the training episodes' success (SB3's
``rollout/success_rate``, from the adapter's ``is_success``); every --eval-every env steps and at the end the
deterministic policy runs --eval-episodes held-out seeds. TensorBoard logs and the model go under --out-dir, after a
Ctrl-C too; a last line sums the run up.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecNormalize

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # agents/configs, beside examples/ in the checkout

from agents.configs import loader  # noqa: E402
from maniskill_irb120.envs import check_env_id  # noqa: E402
from maniskill_irb120.errors import check_count, parse_flags, terminate_as_interrupt, usage_errors  # noqa: E402
from maniskill_irb120.integrations.sb3 import ProgressCallback, make_sb3_vec_env  # noqa: E402

LIBRARY_DEFAULT_ENVS = 2
LIBRARY_DEFAULT_STEPS = 100_000


@dataclass
class Args:
    env_id: str = "GraspLift-IRB120-v1"
    obs: str = "state"
    """state (MlpPolicy) or rgbd (MultiInputPolicy: the hand camera's RGB-D image + a state vector)"""
    library_defaults: bool = False
    """SB3's own PPO settings instead of agents/configs/sb3/ppo.yml (ppo_rgbd.yml from the camera)"""
    num_envs: Optional[int] = None
    """envs stepping side by side (default: the config's, 4; with SB3's defaults 2)"""
    backend: str = "auto"
    """cpu (worker processes), gpu (physx_cuda) or auto"""
    total_timesteps: Optional[int] = None
    """env steps to train (default: the config's n_timesteps; with SB3's defaults 100000)"""
    n_steps: Optional[int] = None
    """steps per env and rollout (default: the config's 128, or SB3's 2048)"""
    eval_every: int = 25_000
    """env steps between held-out checks (0: only at the end)"""
    eval_episodes: int = 10
    """held-out episodes per check (0: none)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    out_dir: Path = Path("runs/sb3_ppo")


def build(args: Args) -> tuple[PPO, str, int]:
    """The model on its envs, what it was configured from, and its env-step budget."""
    config = None
    if not args.library_defaults:
        config = loader.sb3_config("ppo", args.env_id, obs=args.obs)
    envs, steps = (config.n_envs, config.n_timesteps) if config else (LIBRARY_DEFAULT_ENVS, LIBRARY_DEFAULT_STEPS)
    num_envs = envs if args.num_envs is None else args.num_envs  # a 0 given is refused below, not defaulted
    total = steps if args.total_timesteps is None else args.total_timesteps
    check_count("--num-envs", num_envs)
    check_count("--total-timesteps", total)
    env_kw = dict(backend=args.backend, seed=args.seed, reward_mode=args.reward_mode)
    if config:  # its wrappers and VecNormalize
        venv = config.vec_env(args.env_id, num_envs, args.obs, **env_kw)
    else:
        venv = make_sb3_vec_env(args.env_id, num_envs, args.obs, **env_kw)
    kwargs = config.model_kwargs(venv.action_space.shape[0]) if config else {}
    if args.n_steps is not None:  # a rollout smaller than the batch needs a smaller batch
        kwargs["n_steps"] = args.n_steps
        kwargs["batch_size"] = min(kwargs.get("batch_size", 64), args.n_steps * num_envs)
    policy = config.policy if config else ("MlpPolicy" if args.obs == "state" else "MultiInputPolicy")
    model = PPO(policy, venv, seed=args.seed, tensorboard_log=str(args.out_dir), verbose=0, **kwargs)
    source = loader.sb3_path("ppo", args.obs).relative_to(REPO).as_posix() if config else "SB3's defaults"
    return model, source, total


def main(args: Args) -> PPO:
    check_env_id(args.env_id)
    check_count("--eval-every", args.eval_every, least=0)
    check_count("--eval-episodes", args.eval_episodes, least=0)
    model, source, total = build(args)
    venv = model.get_env()
    print(f"[sb3 ppo] {args.env_id} from {args.obs}, {venv.num_envs} envs, {source}; {total:,} env steps", flush=True)
    progress = ProgressCallback(
        total, args.env_id, args.obs, label="sb3 ppo", eval_every=args.eval_every, eval_episodes=args.eval_episodes
    )
    started, interrupted = time.perf_counter(), False
    try:
        model.learn(total, callback=progress)
        if args.eval_episodes:
            progress.check()  # the end's held-out success
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the model learnt so far is saved all the same
        interrupted = True
    model.save(args.out_dir / "model")
    if isinstance(venv, VecNormalize):  # the observation statistics the policy needs, beside it
        venv.save(str(args.out_dir / "vecnormalize.pkl"))
    venv.close()
    steps, seconds = model.num_timesteps, time.perf_counter() - started
    if interrupted:
        print(f"interrupted (Ctrl-C or SIGTERM) at {steps} env steps; model so far: {args.out_dir}/model.zip",
              file=sys.stderr)  # fmt: skip
        raise SystemExit(130)
    successes = list(model.ep_success_buffer)
    held = f"{progress.held[-1][1]}/{progress.held[-1][2]}" if progress.held else "not checked"
    print(
        f"{steps} env steps in {seconds:.0f} s ({steps / seconds:.1f} env steps/s); training-episode success, last "
        f"{len(successes)} episodes: {np.mean(successes or [0]):.2f}; held-out success {held}; "
        f"model: {args.out_dir / 'model.zip'}",
        flush=True,
    )
    return model


if __name__ == "__main__":
    with usage_errors(Path(__file__).name):  # a wrong env id or count: one line, exit status 2
        args = parse_flags(Args, Path(__file__).name)
        with terminate_as_interrupt():  # a SIGTERM (a session's end) saves what was learnt, as Ctrl-C does
            main(args)
