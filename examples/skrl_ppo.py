"""skrl's PPO on a task, from the reward alone, through maniskill_irb120.integrations.skrl (needs the skrl extra).

    .venv/bin/python examples/skrl_ppo.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 200000
    .venv/bin/python examples/skrl_ppo.py --obs rgbd --num-envs 2 --total-timesteps 512 --eval-episodes 2

From state it trains with ``agents/configs/skrl/ppo_<task>.yaml`` through skrl's ``Runner`` (as Isaac Lab's skrl
train script does): the project's tuned settings, 4 envs, a running observation scaler, the absorbing value on
success, 128-step rollouts, gamma 0.8, each setting's reason beside it in the file. ``--library-defaults`` (and the
camera, which the configs were not tuned for) takes skrl's ``PPO_CFG`` as it comes (16 rollout steps per env, 8
epochs, 2 minibatches, gamma 0.99, lambda 0.95) on 2 envs, with the adapter's models, but for
``time_limit_bootstrap``: the tasks cut episodes at a step limit, which is no failure, so a cut-off episode's value
is bootstrapped.

A line every 10 s shows the env steps, their rate, the time left and the training episodes' success (the adapter's
``recent_success``); every --eval-every env steps and at the end the deterministic policy runs --eval-episodes
held-out seeds. TensorBoard logs under --out-dir: skrl's episode length and return, and ``Episode / Success rate
(mean)`` from the adapter; the agent is saved to --out-dir/agent.pt, after a Ctrl-C too, and a last line sums the
run up (env steps, env steps/s, held-out success).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.memories.torch import RandomMemory
from skrl.trainers.torch import SequentialTrainer
from skrl.utils import set_seed

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # agents/configs, beside examples/ in the checkout

from agents.configs import loader  # noqa: E402
from maniskill_irb120.envs import check_env_id  # noqa: E402
from maniskill_irb120.errors import check_count, parse_flags, terminate_as_interrupt, usage_errors  # noqa: E402
from maniskill_irb120.integrations.progress import Heartbeat, Progress, held_out_success  # noqa: E402
from maniskill_irb120.integrations.skrl import (  # noqa: E402
    SUCCESS_KEY,
    deterministic_policy,
    make_skrl_env,
    policy_and_value,
)

LIBRARY_DEFAULT_ENVS = 2
LIBRARY_DEFAULT_STEPS = 100_000


@dataclass
class Args:
    env_id: str = "GraspLift-IRB120-v1"
    obs: str = "state"
    """state (the state vector) or rgbd (the hand camera's RGB-D image + a state vector)"""
    library_defaults: bool = False
    """skrl's own PPO_CFG instead of agents/configs/skrl/ppo_<task>.yaml (the camera always takes it)"""
    num_envs: Optional[int] = None
    """envs stepping side by side (default: the config's, 4; with skrl's defaults 2)"""
    backend: str = "auto"
    """cpu (worker processes), gpu (physx_cuda) or auto"""
    total_timesteps: Optional[int] = None
    """env steps in all (default: the config's; with skrl's defaults 100000). skrl's trainer counts steps of the
    whole batch: this / num_envs"""
    eval_every: int = 25_000
    """env steps between held-out checks (0: only at the end)"""
    eval_episodes: int = 10
    """held-out episodes per check (0: none)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    out_dir: Path = Path("runs/skrl_ppo")


def build(args: Args) -> tuple[Any, PPO, SequentialTrainer, str, int]:
    """The env, the agent, its trainer, what they were configured from, and the env-step budget."""
    config = None
    if not args.library_defaults and args.obs == "state":
        config = loader.skrl_config("ppo", args.env_id)
    config_envs, wrappers = loader.skrl_env_settings(config) if config else (LIBRARY_DEFAULT_ENVS, [])
    num_envs = config_envs if args.num_envs is None else args.num_envs  # a 0 given is refused, not defaulted
    check_count("--num-envs", num_envs)
    steps = config["trainer"]["timesteps"] * num_envs if config else LIBRARY_DEFAULT_STEPS
    total = steps if args.total_timesteps is None else args.total_timesteps  # a 0 given is refused, not defaulted
    check_count("--total-timesteps", total)
    set_seed(args.seed)
    env = make_skrl_env(
        args.env_id, num_envs, args.obs, backend=args.backend, seed=args.seed, reward_mode=args.reward_mode,
        wrappers=wrappers,
    )  # fmt: skip
    # our lines replace skrl's progress bar (integrations.progress says why); the env is closed by main, once
    trainer_cfg = {"timesteps": max(1, total // num_envs), "headless": True, "disable_progressbar": True,
                   "close_environment_at_exit": False}  # fmt: skip
    try:
        if config is not None:
            from maniskill_irb120.integrations.skrl import make_runner

            cfg = loader.skrl_runner_config(config)
            cfg["seed"] = args.seed
            cfg["agent"] = dict(cfg["agent"], experiment=dict(directory=str(args.out_dir), experiment_name=""))
            cfg["trainer"] = dict(cfg["trainer"], **trainer_cfg)
            runner = make_runner(env, cfg)
            for hook in loader.skrl_callbacks(config, args.out_dir / "best"):  # the config's checkpoint selection
                hook.attach(runner.agent, env, args.env_id, args.obs)
            source = f"agents/configs/skrl/ppo_{args.env_id.split('-')[0].lower()}.yaml"
            return env, runner.agent, runner.trainer, source, total
        cfg = PPO_CFG(time_limit_bootstrap=True)
        cfg.experiment.directory = str(args.out_dir)
        memory = RandomMemory(memory_size=cfg.rollouts, num_envs=env.num_envs, device=env.device)
        agent = PPO(
            models=policy_and_value(env),
            memory=memory,
            observation_space=env.observation_space,
            action_space=env.action_space,
            device=env.device,
            cfg=cfg,
        )
        return env, agent, SequentialTrainer(env=env, agents=agent, cfg=trainer_cfg), "skrl's PPO_CFG", total
    except BaseException:
        env.close()
        raise


def main(args: Args) -> PPO:
    check_env_id(args.env_id)  # before skrl's first log line
    check_count("--eval-every", args.eval_every, least=0)
    check_count("--eval-episodes", args.eval_episodes, least=0)
    env, agent, trainer, source, total = build(args)
    print(f"[skrl ppo] {args.env_id} from {args.obs}, {env.num_envs} envs, {source}; {total:,} env steps", flush=True)
    progress, held = Progress("skrl ppo", total), []
    next_eval = args.eval_every

    def check(steps: int) -> None:
        started = time.perf_counter()
        act = deterministic_policy(agent, env.observation_space)
        wins = held_out_success(act, args.env_id, args.obs, args.eval_episodes)
        held.append((steps, wins, args.eval_episodes))
        agent.track_data("Episode / Held-out success", wins / args.eval_episodes)
        took = time.perf_counter() - started
        progress.report(steps, f"held-out success {wins}/{args.eval_episodes} (deterministic; {took:.0f} s)")

    def note() -> str:
        parts = []
        if env.recent_success:
            recent = env.recent_success
            parts.append(f"training success {np.mean(recent):.2f} (last {len(recent)} episodes)")
        if held:
            parts.append(f"held out {held[-1][1]}/{held[-1][2]} at {held[-1][0]:,}")
        return "; ".join(parts)

    post_interaction = agent.post_interaction

    def post_interaction_with_progress(*, timestep: int, timesteps: int) -> None:
        """skrl's own, then our line: the one per-step hook a trainer calls on its agents."""
        nonlocal next_eval
        steps = (timestep + 1) * env.num_envs
        with Heartbeat(progress, steps, "updating the policy"):  # skrl's update runs in here, every rollout
            post_interaction(timestep=timestep, timesteps=timesteps)
        if args.eval_every and args.eval_episodes and next_eval <= steps < total:
            next_eval += args.eval_every * (1 + (steps - next_eval) // args.eval_every)
            check(steps)
        progress.tick(steps, note)

    agent.post_interaction = post_interaction_with_progress
    progress.report(0, "started")
    steps = trainer.cfg.timesteps * env.num_envs
    started, interrupted = time.perf_counter(), False
    try:
        trainer.train()
        if args.eval_episodes:
            check(steps)  # the end's held-out success
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the agent learnt so far is saved all the same
        interrupted = True
    env.close()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    agent.save(str(args.out_dir / "agent.pt"))
    if interrupted:
        print(f"interrupted (Ctrl-C or SIGTERM); the agent so far: {args.out_dir / 'agent.pt'}", file=sys.stderr)
        raise SystemExit(130)
    seconds = time.perf_counter() - started
    held_text = f"{held[-1][1]}/{held[-1][2]}" if held else "not checked"
    print(
        f"{steps} env steps in {seconds:.0f} s ({steps / seconds:.1f} env steps/s); held-out success {held_text}; "
        f"agent: {args.out_dir / 'agent.pt'}; TensorBoard ({SUCCESS_KEY!r} among them): {agent.experiment_dir}",
        flush=True,
    )
    return agent


if __name__ == "__main__":
    torch.set_num_threads(1)
    with usage_errors(Path(__file__).name):  # a wrong env id or count: one line, exit status 2
        args = parse_flags(Args, Path(__file__).name)
        with terminate_as_interrupt():  # a SIGTERM (a session's end) saves what was learnt, as Ctrl-C does
            main(args)
