"""Stable-Baselines3's SAC on a task, from the reward alone, through maniskill_irb120.integrations.sb3 (needs the
sb3 extra).

    .venv/bin/python examples/sb3_sac.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 62500
    .venv/bin/python examples/sb3_sac.py --obs rgbd --learning-starts 64 --total-timesteps 256 --eval-episodes 2

From state it trains with ``agents/configs/sb3/sac.yml`` (rl-zoo3's format, read by ``agents/configs/loader.py``):
the project's tuned settings, 4 envs, ``VecNormalize`` on the observations, the absorbing value on success, gamma 0.8,
4000 random steps first, each setting's reason beside it in the file. ``--library-defaults`` (and the camera, which
the configs were not tuned for) takes SB3's SAC as it comes: batch 256, one update per env step, gamma 0.99, tau
0.005, learned entropy, 100 random steps first, on 2 envs. On the camera the replay buffer holds --buffer-size
transitions (SB3's 1e6 would be 57 GB of 4x84x84 images; 30 000 are 1.7 GB). SB3 keeps a cut-off episode's last
transition non-terminal from the adapter's ``TimeLimit.truncated`` and ``terminal_observation``.

A line every 10 s shows the env steps, their rate, the time left (the random warm-up before ``learning_starts``
named as such: it is quick, the updates after it are not, so the ETA grows once they start) and the training
episodes' success (SB3's ``rollout/success_rate``, from the adapter's ``is_success``); every --eval-every env steps
and at the end the deterministic policy runs --eval-episodes held-out seeds. TensorBoard logs and the model go under
--out-dir, after a Ctrl-C too; a last line sums the run up.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import VecNormalize

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # agents/configs, beside examples/ in the checkout

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
    """SB3's own SAC settings instead of agents/configs/sb3/sac.yml (the camera always takes them)"""
    num_envs: Optional[int] = None
    """envs stepping side by side (default: the config's, 4; with SB3's defaults 2)"""
    backend: str = "auto"
    """cpu (worker processes), gpu (physx_cuda) or auto"""
    total_timesteps: Optional[int] = None
    """env steps to train (default: the config's n_timesteps; with SB3's defaults 100000)"""
    learning_starts: Optional[int] = None
    """random env steps before the first update (default: the config's 4000, or SB3's 100)"""
    buffer_size: Optional[int] = None
    """replay transitions (default SB3's 1 000 000 on state, 30 000 on rgbd)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    eval_every: int = 25_000
    """env steps between held-out checks (0: only at the end)"""
    eval_episodes: int = 10
    """held-out episodes per check (0: none)"""
    out_dir: Path = Path("runs/sb3_sac")


def build(args: Args) -> tuple[SAC, str, int]:
    """The model on its envs, what it was configured from, and its env-step budget."""
    config = None
    if not args.library_defaults and args.obs == "state":
        config = loader.sb3_config("sac", args.env_id)
    envs, steps = (config.n_envs, config.n_timesteps) if config else (LIBRARY_DEFAULT_ENVS, LIBRARY_DEFAULT_STEPS)
    num_envs = envs if args.num_envs is None else args.num_envs  # a 0 given is refused below, not defaulted
    total = steps if args.total_timesteps is None else args.total_timesteps
    check_count("--num-envs", num_envs)
    check_count("--total-timesteps", total)
    if args.learning_starts is not None:
        check_count("--learning-starts", args.learning_starts, least=0)
    if args.buffer_size is not None:
        check_count("--buffer-size", args.buffer_size)
    env_kw = dict(backend=args.backend, seed=args.seed, reward_mode=args.reward_mode)
    if config:  # its wrappers and VecNormalize
        venv = config.vec_env(args.env_id, num_envs, args.obs, **env_kw)
    else:
        venv = make_sb3_vec_env(args.env_id, num_envs, args.obs, **env_kw)
    kwargs = config.model_kwargs(venv.action_space.shape[0]) if config else {"learning_starts": 100}
    if args.learning_starts is not None:
        kwargs["learning_starts"] = args.learning_starts
    kwargs["buffer_size"] = args.buffer_size or (1_000_000 if args.obs == "state" else 30_000)
    policy = config.policy if config else ("MlpPolicy" if args.obs == "state" else "MultiInputPolicy")
    model = SAC(policy, venv, seed=args.seed, tensorboard_log=str(args.out_dir), verbose=0, **kwargs)
    source = "agents/configs/sb3/sac.yml" if config else "SB3's defaults"
    return model, source, total


def main(args: Args) -> SAC:
    check_env_id(args.env_id)
    check_count("--eval-every", args.eval_every, least=0)
    check_count("--eval-episodes", args.eval_episodes, least=0)
    model, source, total = build(args)
    venv = model.get_env()
    print(
        f"[sb3 sac] {args.env_id} from {args.obs}, {venv.num_envs} envs, {source}; {total:,} env steps, the first "
        f"{model.learning_starts:,} random",
        flush=True,
    )
    progress = ProgressCallback(
        total, args.env_id, args.obs, label="sb3 sac", eval_every=args.eval_every, eval_episodes=args.eval_episodes
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
