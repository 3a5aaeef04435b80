"""Ray RLlib (new API stack) on our tasks: PPO, APPO or SAC, from one process to a Ray cluster. Its ``Args``
extend the shared ``RunArgs`` (the same task, budget, run folder, resume and ``--evaluate`` flags as every
trainer); it runs ``Algorithm.train()`` in this process (no Tune), logs under agents.ppo's metric names and keeps
RLlib's own checkpoints (``save_to_path``). See docs/rl_libraries.md and docs/training.md.

    python -m agents.rllib --iterations 20                                   # PPO, state, this process samples
    python -m agents.rllib --algo SAC --num-env-runners 2 --total-env-steps 100000   # two env-runner processes
    python -m agents.rllib --resume runs/NAME/checkpoints/latest --iterations 40
    python -m agents.rllib --evaluate --checkpoint runs/NAME/checkpoints/latest --eval-episodes 20
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import torch

from agents.common import EVAL_SEED, Logger, RunArgs, check_budget, evaluate_on_seeds, finish, new_eval_dir
from agents.rllib.checkpoint import checkpoint_args, load_module, module_policy, save_checkpoint
from agents.rllib.env import ENV_NAME, register

ROOT = Path(__file__).resolve().parents[2]
CKPT_EXCLUDES = ["runs/", ".venv/", ".git/", "videos/", "*.mp4", "*.h5", "__pycache__/"]


@dataclass
class Args(RunArgs):
    algo: Literal["PPO", "APPO", "SAC"] = "PPO"
    """RLlib algorithm; each runs on both --obs modes"""
    obs: Literal["state", "rgbd"] = "state"
    """state: RLlib's default MLP; rgbd: 84x84 RGB-D + proprioception through the shared NatureCNN"""
    num_env_runners: int = 0
    """env-runner processes (0: sample in this process); each takes one CPU of the Ray cluster"""
    num_envs_per_env_runner: int = 1
    """envs each runner steps in lockstep (gymnasium sync vector env, or one batched env: --vector-backend)"""
    vector_backend: Optional[Literal["gpu", "cpu"]] = None
    """opt-in: each runner drives one batched ManiSkill env (gpu: physx_cuda; cpu: our worker processes)
    through agents.rllib.env.NextStepAutoreset, RLlib's vector entry point"""
    num_gpus_per_env_runner: Optional[float] = None
    """GPUs for each env runner (default: 1 with --vector-backend gpu and remote runners, else 0)"""
    num_learners: int = 0
    """remote learner processes (0: learn in this process)"""
    num_gpus_per_learner: float = 0.0
    """GPUs for each learner (or for this process when --num-learners 0)"""
    address: Optional[str] = None
    """None: a local Ray sized to this machine; 'auto' or 'host:port': join a running cluster, shipping this
    repository to it as the runtime_env working_dir"""
    num_cpus: Optional[int] = None
    """CPUs of the local Ray (default: this machine's, at least runners + learners)"""
    iterations: Optional[int] = None
    """stop after this many training iterations in all (counting a resumed run's); default 100 when no
    --total-env-steps, --max-minutes or --budget-min is given"""
    gamma: float = 0.9
    """discount; our episodes are ~75 steps (ManiSkill's PPO default 0.8 is for shorter horizons)"""
    lr: float = 3e-4
    gae_lambda: float = 0.9
    """PPO/APPO: GAE lambda (agents.ppo's default)"""
    train_batch_size: Optional[int] = None
    """env steps per learner update (PPO/APPO) or transitions per SGD batch (SAC); None: RLlib's default"""
    minibatch_size: Optional[int] = None
    """PPO/APPO SGD minibatch (None: RLlib's default)"""
    num_epochs: Optional[int] = None
    """PPO/APPO passes over each batch (None: RLlib's default)"""
    rollout_fragment_length: Union[int, Literal["auto"]] = "auto"
    """steps each env collects per sample() call (auto: RLlib sizes it to the batch; APPO: 50)"""
    learning_starts: int = 1000
    """SAC: env steps in the replay buffer before the first update"""
    replay_capacity: int = 100_000
    """SAC: replay buffer size in transitions"""
    checkpoint_freq: int = 10
    """save a checkpoint every N iterations (and always at the end)"""
    max_env_runner_restarts: int = 100
    """fault tolerance: a crashed env runner is restarted (up to this many times) and training goes on"""
    eval_episodes: int = 0
    """after training (or with --evaluate; default 10 there): deterministic episodes on held-out seeds
    (agents.common.EVAL_SEED onwards); their success_rate ends the printed JSON"""


NOT_HERE = dict(select_episodes=0, device="auto", backend="auto", recipe=None)
"""RunArgs flags RLlib sizes its own way (--num-gpus-per-learner, --vector-backend) or has no part for (selection,
recipes): anything but their default is refused"""


def env_config(args: Args) -> dict:
    cfg = dict(env_id=args.env_id, obs=args.obs, env_kwargs=dict(args.env_kwargs))
    if args.vector_backend is not None:
        cfg["vector_backend"] = args.vector_backend
    return cfg


def build_config(args: Args):
    """The AlgorithmConfig for ``args``, without starting Ray (so it can be built and validated in tests)."""
    import gymnasium as gym
    from ray.rllib.algorithms.appo import APPOConfig
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.algorithms.sac import SACConfig

    from agents.rllib.callbacks import TaskMetrics
    from agents.rllib.module import module_spec

    if args.num_env_runners < 0 or args.num_envs_per_env_runner < 1 or args.num_learners < 0:
        raise ValueError("need --num-env-runners >= 0, --num-envs-per-env-runner >= 1 and --num-learners >= 0")
    if args.algo == "APPO" and args.num_env_runners < 1:
        raise ValueError("APPO samples asynchronously on remote env runners: give --num-env-runners >= 1")
    configs = {"PPO": PPOConfig, "APPO": APPOConfig, "SAC": SACConfig}
    if args.algo not in configs:
        raise ValueError(f"unknown --algo {args.algo!r}; use one of {sorted(configs)}")
    cfg = configs[args.algo]()
    cfg.environment(ENV_NAME, env_config=env_config(args))
    cfg.framework("torch")
    fragment = args.rollout_fragment_length
    if args.algo == "APPO" and fragment == "auto":
        fragment = 50  # APPO's own default; its minibatch must be a multiple of a numeric fragment length
    runners = dict(
        num_env_runners=args.num_env_runners,
        num_envs_per_env_runner=args.num_envs_per_env_runner,
        rollout_fragment_length=fragment,
    )
    if args.vector_backend is not None:
        runners["gym_env_vectorize_mode"] = gym.VectorizeMode.VECTOR_ENTRY_POINT
    gpus = args.num_gpus_per_env_runner
    if gpus is None:
        gpus = 1.0 if args.vector_backend == "gpu" and args.num_env_runners > 0 else 0.0
    runners["num_gpus_per_env_runner"] = gpus
    cfg.env_runners(**runners)
    cfg.learners(num_learners=args.num_learners, num_gpus_per_learner=args.num_gpus_per_learner)
    cfg.rl_module(rl_module_spec=module_spec(args.algo))
    train = dict(gamma=args.gamma, lr=args.lr)
    if args.train_batch_size is not None:
        train["train_batch_size_per_learner"] = args.train_batch_size
    if args.algo in ("PPO", "APPO"):
        train["lambda_"] = args.gae_lambda
        if args.minibatch_size is not None:
            train["minibatch_size"] = args.minibatch_size
        if args.num_epochs is not None:
            train["num_epochs"] = args.num_epochs
    else:
        train.update(
            actor_lr=args.lr,
            critic_lr=args.lr,
            alpha_lr=args.lr,
            num_steps_sampled_before_learning_starts=args.learning_starts,
            replay_buffer_config={"type": "PrioritizedEpisodeReplayBuffer", "capacity": args.replay_capacity},
        )
        train.pop("lr")
    cfg.training(**train)
    cfg.callbacks(TaskMetrics)
    cfg.fault_tolerance(
        restart_failed_env_runners=True,
        max_num_env_runner_restarts=args.max_env_runner_restarts,
    )
    cfg.debugging(seed=args.seed)
    return cfg


def init_ray(args: Args) -> None:
    """A local Ray sized so every runner and learner gets its CPU, or a connection to a cluster that gets
    this repository shipped to it (its workers then import ``agents`` from the shipped copy)."""
    import ray

    if ray.is_initialized():
        return
    # env runners import agents.* (the callback, the catalog) by name: on this machine they find it here
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    if args.address is None:
        need = args.num_env_runners + args.num_learners
        num_cpus = args.num_cpus or max(os.cpu_count() or 1, need)
        if num_cpus < need:
            raise ValueError(f"--num-cpus {num_cpus} < {need} (one per env runner and remote learner)")
        ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=True)
    else:
        ray.init(address=args.address, runtime_env={"working_dir": str(ROOT), "excludes": CKPT_EXCLUDES})


def held_out_eval(args: Args, path: Path, episodes: int, video_dir: Optional[Path]) -> dict:
    saved = checkpoint_args(path, args, ("obs", "env_id"))
    module = load_module(path)
    module.eval()
    seeds = [EVAL_SEED + i for i in range(episodes)]
    env_kwargs = dict(reward_mode="normalized_dense", **saved.get("env_kwargs", {}))
    return evaluate_on_seeds(
        module_policy(module, args.obs), args.env_id, args.obs, seeds, video_dir=video_dir, **env_kwargs
    )


def evaluate(args: Args) -> dict:
    """``--evaluate --checkpoint PATH``: held-out episodes with videos; ``summary.json`` beside the run, like
    agents.ppo."""
    if args.checkpoint is None:
        raise ValueError("--evaluate needs --checkpoint PATH (an agents.rllib checkpoint folder)")
    path = Path(args.checkpoint)
    out_dir = new_eval_dir(path.resolve().parent.parent)
    result = held_out_eval(args, path, args.eval_episodes or 10, out_dir / "videos" if args.capture_video else None)
    result["checkpoint"] = str(path)
    result["eval_dir"] = str(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return finish(result, out_dir)


def scalars_of(result: dict) -> dict[str, float]:
    """One training result as TensorBoard scalars under agents.ppo's names (train/..., losses/..., charts/...)."""
    from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, LEARNER_RESULTS

    runners = result.get(ENV_RUNNER_RESULTS, {})
    out = {}
    for k, v in runners.items():
        if (k.endswith("_rate") or k.startswith("return_r_")) and np.isfinite(v):
            out[f"train/{k}"] = float(v)
    for ours, theirs in (("return", "episode_return_mean"), ("episode_len", "episode_len_mean")):
        if theirs in runners and np.isfinite(runners[theirs]):  # NaN: no episode ended in the window yet
            out[f"train/{ours}"] = float(runners[theirs])
    for k, v in result.get(LEARNER_RESULTS, {}).get("default_policy", {}).items():
        if isinstance(v, (int, float, np.floating)) and np.isfinite(v):
            out[f"losses/{k}"] = float(v)
    return out


def env_steps_of(result: dict) -> int:
    from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME

    return int(result.get(ENV_RUNNER_RESULTS, {}).get(NUM_ENV_STEPS_SAMPLED_LIFETIME, 0))


def main(args: Args) -> dict:
    for name, default in NOT_HERE.items():
        if getattr(args, name) != default:
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"{flag} is not an agents.rllib flag (RLlib's runs leave it at {default})")
    if args.evaluate:
        return evaluate(args)
    check_budget(args)
    total = args.total_env_steps
    guard_min = args.max_minutes if args.max_minutes is not None else args.budget_min
    if args.iterations is None and total is None and guard_min is None:
        args.iterations = 100
    config = build_config(args)  # argument errors before Ray starts
    if args.resume is not None:
        checkpoint_args(args.resume, args, ("algo", "obs", "env_id"))
    name = args.exp_name or f"rllib_{args.algo}__{args.env_id}__{args.obs}__{args.seed}__{int(time.time())}"
    run_dir = Path(args.runs_dir) / name
    ckpt_dir = run_dir / "checkpoints"
    torch.manual_seed(args.seed)
    init_ray(args)
    register()
    algo = config.build_algo()
    if args.resume is not None:
        algo.restore_from_path(str(Path(args.resume).resolve()))
    run_dir.mkdir(parents=True, exist_ok=True)
    logger = Logger(run_dir, args)
    bar = None
    if args.progress:
        from tqdm import tqdm

        bar = tqdm(total=args.iterations, initial=algo.iteration, unit="iter", desc=f"rllib {args.algo}")
    t0, result, latest, saved_at = time.time(), {}, None, None
    env_steps, stopped_early = 0, False
    try:
        while True:
            if args.iterations is not None and algo.iteration >= args.iterations:
                break
            if total is not None and env_steps >= total:
                break
            if guard_min is not None and time.time() - t0 >= 60 * guard_min:
                stopped_early = total is not None
                break
            t_iter, steps_before = time.time(), env_steps
            result = algo.train()
            env_steps = env_steps_of(result)
            scalars = scalars_of(result)
            scalars["charts/SPS"] = (env_steps - steps_before) / max(time.time() - t_iter, 1e-9)
            logger.scalars(scalars, env_steps)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(steps=env_steps, success=f"{scalars.get('train/success_rate', float('nan')):.2f}")
            if algo.iteration % args.checkpoint_freq == 0:
                latest, saved_at = save_checkpoint(algo, ckpt_dir, args), algo.iteration
    finally:
        # Ctrl-C or a crash still leaves the last complete iteration on disk
        if algo.iteration > 0 and algo.iteration != saved_at:
            latest = save_checkpoint(algo, ckpt_dir, args)
        if bar is not None:
            bar.close()
        logger.close()
        algo.stop()
    summary = dict(
        algo=args.algo,
        obs=args.obs,
        iterations=algo.iteration,
        env_steps=env_steps,
        checkpoint=str(latest) if latest else None,
        train_success_rate=scalars_of(result).get("train/success_rate"),
        wall_clock_s=round(time.time() - t0, 1),
        total_env_steps=total,
        max_minutes=guard_min,
        stopped_early=stopped_early,
    )
    if stopped_early:
        print(f"stopped early at {env_steps} env steps (of {total})", flush=True)
    summary["success_rate"] = summary["train_success_rate"]
    if args.eval_episodes > 0 and latest is not None:
        final = held_out_eval(args, latest, args.eval_episodes, None)
        summary.update(success_rate=final["success_rate"], eval=final)
    return finish(summary, run_dir)
