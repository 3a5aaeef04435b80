"""skrl's PPO on a task, from the reward alone, through maniskill_irb120.integrations.skrl (needs the skrl extra).

    .venv/bin/python examples/skrl_ppo.py --env-id GraspLift-IRB120-v1 --obs state --total-timesteps 200000
    .venv/bin/python examples/skrl_ppo.py --obs rgbd --num-envs 2 --total-timesteps 512   # a quick look

skrl's PPO configuration as it comes (``PPO_CFG``'s defaults: 16 rollout steps per env, 8 epochs, 2 minibatches,
gamma 0.99, lambda 0.95) but for ``time_limit_bootstrap``: the tasks cut episodes at a step limit, which is no
failure, so a cut-off episode's value is bootstrapped. TensorBoard logs under --out-dir: skrl's episode length and
return, and ``Episode / Success rate (mean)`` from the adapter; the agent is saved to --out-dir/agent.pt, after a
Ctrl-C too, and a last line sums the run up (env steps, env steps/s).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.memories.torch import RandomMemory
from skrl.trainers.torch import SequentialTrainer
from skrl.utils import set_seed

from maniskill_irb120.envs import check_env_id
from maniskill_irb120.errors import check_count, parse_flags, usage_errors
from maniskill_irb120.integrations.skrl import SUCCESS_KEY, make_skrl_env, policy_and_value


@dataclass
class Args:
    env_id: str = "GraspLift-IRB120-v1"
    obs: str = "state"
    """state (the state vector) or rgbd (the hand camera's RGB-D image + a state vector)"""
    num_envs: int = 2
    backend: str = "auto"
    """cpu (worker processes), gpu (physx_cuda) or auto"""
    total_timesteps: int = 100_000
    """env steps in all (skrl's trainer counts steps of the whole batch: this / num_envs)"""
    seed: int = 1
    reward_mode: Optional[str] = None
    """the task's reward (default normalized_dense)"""
    out_dir: Path = Path("runs/skrl_ppo")


def main(args: Args) -> PPO:
    check_count("--num-envs", args.num_envs)
    check_count("--total-timesteps", args.total_timesteps)
    check_env_id(args.env_id)  # before skrl's first log line
    set_seed(args.seed)
    env = make_skrl_env(
        args.env_id, args.num_envs, args.obs, backend=args.backend, seed=args.seed, reward_mode=args.reward_mode
    )
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
    steps = max(1, args.total_timesteps // env.num_envs)
    trainer = SequentialTrainer(
        env=env, agents=agent, cfg={"timesteps": steps, "headless": True, "close_environment_at_exit": False}
    )
    started, interrupted = time.perf_counter(), False
    try:
        trainer.train()  # skrl's progress bar: the batch's steps, steps/s and the time left
    except KeyboardInterrupt:  # Ctrl-C: the agent learnt so far is saved all the same
        interrupted = True
    env.close()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    agent.save(str(args.out_dir / "agent.pt"))
    if interrupted:
        print(f"interrupted (Ctrl-C); the agent so far: {args.out_dir / 'agent.pt'}", file=sys.stderr)
        raise SystemExit(130)
    seconds = time.perf_counter() - started
    print(
        f"{steps * env.num_envs} env steps in {seconds:.0f} s ({steps * env.num_envs / seconds:.1f} env steps/s); "
        f"agent: {args.out_dir / 'agent.pt'}; TensorBoard ({SUCCESS_KEY!r} among them): {agent.experiment_dir}"
    )
    return agent


if __name__ == "__main__":
    torch.set_num_threads(1)
    with usage_errors(Path(__file__).name):  # a wrong env id or count: one line, exit status 2
        main(parse_flags(Args, Path(__file__).name))
