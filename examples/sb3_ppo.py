"""Stable-Baselines3's PPO on a task, from the reward alone, through maniskill_irb120.integrations.sb3 (needs the
sb3 extra).

    .venv/bin/python examples/sb3_ppo.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 200000
    .venv/bin/python examples/sb3_ppo.py --obs rgbd --n-steps 64 --total-timesteps 256   # a quick look

SB3's PPO defaults (``n_steps=2048`` per env, batch 64, 10 epochs, gamma 0.99, lambda 0.95): ``MlpPolicy`` on the
state vector, ``MultiInputPolicy`` (``NatureCNN`` on the RGB-D image, the state beside it) on the camera. SB3
bootstraps an episode cut at the step limit from the adapter's ``TimeLimit.truncated``. TensorBoard logs under
--out-dir (``rollout/success_rate`` from the adapter's ``is_success``); the model is saved there, after a Ctrl-C
too. SB3's progress bar shows the env steps, their rate and the time left.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from stable_baselines3 import PPO

from maniskill_irb120.errors import check_count, parse_flags, usage_errors
from maniskill_irb120.integrations.sb3 import make_sb3_vec_env


@dataclass
class Args:
    env_id: str = "GraspLift-IRB120-v1"
    obs: str = "state"
    """state (MlpPolicy) or rgbd (MultiInputPolicy: the hand camera's RGB-D image + a state vector)"""
    num_envs: int = 2
    backend: str = "auto"
    """cpu (worker processes), gpu (physx_cuda) or auto"""
    total_timesteps: int = 100_000
    n_steps: Optional[int] = None
    """steps per env and rollout (default SB3's 2048)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    out_dir: Path = Path("runs/sb3_ppo")


def main(args: Args) -> PPO:
    check_count("--num-envs", args.num_envs)
    check_count("--total-timesteps", args.total_timesteps)
    venv = make_sb3_vec_env(
        args.env_id, args.num_envs, args.obs, backend=args.backend, seed=args.seed, reward_mode=args.reward_mode
    )
    policy = "MlpPolicy" if args.obs == "state" else "MultiInputPolicy"
    extra = {}
    if args.n_steps is not None:  # a rollout smaller than SB3's batch of 64 needs a smaller batch
        extra = {"n_steps": args.n_steps, "batch_size": min(64, args.n_steps * args.num_envs)}
    model = PPO(policy, venv, seed=args.seed, tensorboard_log=str(args.out_dir), verbose=1, **extra)
    started, interrupted = time.perf_counter(), False
    try:
        model.learn(args.total_timesteps, progress_bar=True)  # env steps, steps/s and the time left
    except KeyboardInterrupt:  # Ctrl-C: the model learnt so far is saved all the same
        interrupted = True
    model.save(args.out_dir / "model")
    venv.close()
    steps, seconds = model.num_timesteps, time.perf_counter() - started
    if interrupted:
        print(f"interrupted (Ctrl-C) at {steps} env steps; model so far: {args.out_dir}/model.zip", file=sys.stderr)
        raise SystemExit(130)
    successes = list(model.ep_success_buffer)
    print(
        f"{steps} env steps in {seconds:.0f} s ({steps / seconds:.1f} env steps/s); training-episode success, last "
        f"{len(successes)} episodes: {np.mean(successes or [0]):.2f}; model: {args.out_dir / 'model.zip'}"
    )
    return model


if __name__ == "__main__":
    with usage_errors(Path(__file__).name):  # a wrong env id or count: one line, exit status 2
        main(parse_flags(Args, Path(__file__).name))
