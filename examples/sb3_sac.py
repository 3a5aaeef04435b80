"""Stable-Baselines3's SAC on a task, from the reward alone, through maniskill_irb120.integrations.sb3 (needs the
sb3 extra).

    .venv/bin/python examples/sb3_sac.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 200000
    .venv/bin/python examples/sb3_sac.py --obs rgbd --learning-starts 64 --total-timesteps 256   # a quick look

SB3's SAC defaults (batch 256, one update per env step, gamma 0.99, tau 0.005, learned entropy, 100 random steps
first): ``MlpPolicy`` on the state vector, ``MultiInputPolicy`` on the camera, whose replay buffer holds
--buffer-size transitions (SB3's 1e6 would be 57 GB of 4x84x84 images; 30 000 are 1.7 GB). SB3 keeps a cut-off
episode's last transition non-terminal from the adapter's ``TimeLimit.truncated`` and ``terminal_observation``.
SB3's progress bar shows the env steps, their rate and the time left (on the camera, the first --learning-starts
steps are quick and the updates slow); the model is saved under --out-dir, after a Ctrl-C too.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from stable_baselines3 import SAC

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
    learning_starts: int = 100
    buffer_size: Optional[int] = None
    """replay transitions (default SB3's 1 000 000 on state, 30 000 on rgbd)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    out_dir: Path = Path("runs/sb3_sac")


def main(args: Args) -> SAC:
    check_count("--num-envs", args.num_envs)
    check_count("--total-timesteps", args.total_timesteps)
    venv = make_sb3_vec_env(
        args.env_id, args.num_envs, args.obs, backend=args.backend, seed=args.seed, reward_mode=args.reward_mode
    )
    policy = "MlpPolicy" if args.obs == "state" else "MultiInputPolicy"
    buffer_size = args.buffer_size or (1_000_000 if args.obs == "state" else 30_000)
    model = SAC(
        policy,
        venv,
        buffer_size=buffer_size,
        learning_starts=args.learning_starts,
        seed=args.seed,
        tensorboard_log=str(args.out_dir),
        verbose=1,
    )
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
