"""RLlib against our own trainer on the same machine, in the same run (state obs, TableClearing-IRB120-v1).

For RLlib PPO with 0/1/2 env runners x 1/2 envs each: start-up time (``build_algo``), env steps/s *sampled*
(every runner's ``sample()`` in parallel, the policy in the loop), env steps/s *trained* (whole
``Algorithm.train()`` iterations), RSS per env-runner process, and where a sampled step's time goes (RLlib's
own timers). Reference in the same run: our CPU vector env (``make_vec_env``, W worker processes) stepped by
``agents.ppo``'s policy network (sampled), and ``agents.ppo`` training iterations (trained), W = 1, 2.

Target (issue 13): RLlib sampling with 2 env runners >= 0.8x our vector env with 2 workers, measured in alternating
turns with both kept running (the grid above runs minutes apart; these machines drift by up to 1.7x over minutes).

    python -m benchmarks.rllib_speed                      # ~6 min on 2 cores
    python -m benchmarks.rllib_speed --quick --json /tmp/r.json
    python -m benchmarks.rllib_speed --update-results     # also rewrites its section of RESULTS.md
    python -m benchmarks.rllib_speed --render-only        # rewrites the section from --json, measuring nothing
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.report import RESULTS, raw_link, replace_section

ROOT = Path(__file__).resolve().parents[1]

ENV_ID = "TableClearing-IRB120-v1"
HEAD = "## Ray RLlib against our trainer — `benchmarks/rllib_speed.py`"


@dataclass
class Args:
    steps: int = 400
    """env steps each runner (or each of our workers) samples per timed round"""
    iterations: int = 3
    """timed training iterations per configuration (after one untimed warm-up iteration)"""
    batch: int = 400
    """env steps per training iteration, RLlib and agents.ppo alike"""
    rounds: int = 2
    """repeat the whole grid; the table shows each configuration's median"""
    paired_steps: int = 1000
    """the target's comparison: steps per env in each alternating turn"""
    paired_rounds: int = 5
    """the target's comparison: alternating turns of ours and RLlib's (the ratio is their median)"""
    quick: bool = False
    """tiny sizes, 0/1 runners only: checks the script runs and writes well-formed JSON"""
    json: Path = ROOT / "benchmarks" / "results" / "rllib_speed.json"
    update_results: bool = False
    """rewrite this benchmark's section of benchmarks/RESULTS.md"""
    render_only: bool = False
    """measure nothing: rewrite the section of benchmarks/RESULTS.md from the JSON at --json"""


def rss_mb(pid: Optional[int] = None) -> float:
    import psutil

    return psutil.Process(pid or os.getpid()).memory_info().rss / 2**20


def our_sampler(workers: int):
    """Our CPU vector env of ``workers`` processes and agents.ppo's (untrained) network: (venv, step), where
    ``step(n)`` samples ``n`` steps per env with the network and returns the seconds it took."""
    from agents.ppo import Agent
    from maniskill_irb120.vector import make_vec_env

    venv = make_vec_env(ENV_ID, workers, backend="cpu", obs_mode="state", render_backend="none", record_metrics=False)
    agent = Agent(None, venv.single_observation_space.shape[0], 5)
    obs = venv.reset(seed=0)[0]

    def step(n: int) -> float:
        nonlocal obs
        t0 = time.perf_counter()
        with torch.no_grad():
            for _ in range(n):
                obs, *_ = venv.step(agent.get_action({"state": obs.float()}).clamp(-1, 1))
        return time.perf_counter() - t0

    return venv, step


def ours(workers: int, args: Args) -> dict:
    """Our CPU vector env of ``workers`` processes, stepped by agents.ppo's network (sampled), then
    agents.ppo's own training iterations (trained: rollout + update, its charts/SPS)."""
    t0 = time.perf_counter()
    venv, step = our_sampler(workers)
    startup = time.perf_counter() - t0
    step(10)  # warm-up
    sampled = workers * args.steps / step(args.steps)
    venv.close()
    trained = ppo_trained(workers, args)
    return dict(
        trainer="agents.ppo", runners=workers, envs_per_runner=1, startup_s=startup, sampled=sampled, trained=trained
    )


def ppo_trained(workers: int, args: Args) -> float:
    import tempfile

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from agents import ppo

    with tempfile.TemporaryDirectory() as d:
        a = ppo.Args(
            obs="state",
            num_envs=workers,
            num_steps=args.batch // workers,
            update_epochs=1,
            total_env_steps=args.batch * (args.iterations + 1),
            eval_freq=0,
            eval_freq_episodes=0,
            capture_video=False,
            progress=False,
            runs_dir=Path(d),
            exp_name="p",
            save_freq=1000,
        )
        ppo.main(a)
        ea = EventAccumulator(str(Path(d) / "p"))
        ea.Reload()
        return statistics.median(s.value for s in ea.Scalars("charts/SPS")[1:])


@contextlib.contextmanager
def own_torch_determinism():
    """RLlib seeds torch on a CPU build with ``torch.use_deterministic_algorithms(True)`` for the whole process
    (``ray.rllib.utils.torch_utils.set_torch_seed``), and under it every ``torch.empty`` fills its memory and some ops
    take slower paths. RLlib keeps that setting while it runs here, as in its own process; on the way out the setting
    is put back, so this process's ``agents.ppo`` turns (the next round's) run as ``agents.ppo`` runs alone."""
    before = torch.are_deterministic_algorithms_enabled()
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before)


def rllib(runners: int, envs: int, args: Args) -> dict:
    from agents.rllib.train import Args as RArgs
    from agents.rllib.train import build_config

    cfg = build_config(
        RArgs(
            num_env_runners=runners,
            num_envs_per_env_runner=envs,
            train_batch_size=args.batch,
            minibatch_size=args.batch // 4,
            num_epochs=1,
        )
    )
    with own_torch_determinism():
        return rllib_measured(cfg, runners, envs, args)


def rllib_measured(cfg, runners: int, envs: int, args: Args) -> dict:
    """:func:`rllib`'s measurement of the built config."""
    t0 = time.perf_counter()
    algo = cfg.build_algo()
    startup = time.perf_counter() - t0
    group = algo.env_runner_group
    local = runners == 0
    per = max(args.steps // envs, 1) * envs
    try:
        group.foreach_env_runner(lambda r: r.sample(num_timesteps=50), local_env_runner=local)  # warm-up
        t0 = time.perf_counter()
        group.foreach_env_runner(lambda r: r.sample(num_timesteps=per), local_env_runner=local)
        sampled = per * max(runners, 1) / (time.perf_counter() - t0)
        rss = group.foreach_env_runner(
            lambda r: __import__("psutil").Process().memory_info().rss / 2**20, local_env_runner=local
        )
        result = algo.train()
        steps0, t0 = result["env_runners"]["num_env_steps_sampled_lifetime"], time.perf_counter()
        for _ in range(args.iterations):
            result = algo.train()
        trained = (result["env_runners"]["num_env_steps_sampled_lifetime"] - steps0) / (time.perf_counter() - t0)
        er = result["env_runners"]
        per_step_ms = dict(
            env_step=1e3 * er.get("env_step_timer", float("nan")),
            inference=1e3 * er.get("rlmodule_inference_timer", float("nan")),
            connectors=1e3
            * (
                er.get("env_to_module_connector", {}).get("connector_pipeline_timer", 0.0)
                + er.get("module_to_env_connector", {}).get("connector_pipeline_timer", 0.0)
            ),
        )
        per_step_ms["total"] = 1e3 * max(runners, 1) * envs / sampled  # one step of a runner's envs
    finally:
        algo.stop()
    return dict(
        trainer="rllib PPO",
        runners=runners,
        envs_per_runner=envs,
        startup_s=startup,
        sampled=sampled,
        trained=trained,
        rss_mb_per_runner=float(np.mean(rss)),
        per_step_ms=per_step_ms,
    )


def paired(args: Args) -> dict:
    """The target's comparison, alternated: our 2-worker vector env and RLlib's 2 env runners both stay up and
    take turns sampling ``paired_steps`` steps per env, so a drifting machine slows both sides of each ratio."""
    from agents.rllib.train import Args as RArgs
    from agents.rllib.train import build_config

    n = args.paired_steps
    venv, step = our_sampler(2)
    cfg = RArgs(num_env_runners=2, train_batch_size=args.batch, minibatch_size=args.batch // 4, num_epochs=1)
    with own_torch_determinism():  # its runners are their own processes: this one's setting stays ours
        algo = build_config(cfg).build_algo()
    group = algo.env_runner_group
    ours, theirs = [], []
    try:
        group.foreach_env_runner(lambda r: r.sample(num_timesteps=50), local_env_runner=False)
        for _ in range(args.paired_rounds):
            ours.append(2 * n / step(n))
            t0 = time.perf_counter()
            group.foreach_env_runner(lambda r: r.sample(num_timesteps=n), local_env_runner=False)
            theirs.append(2 * n / (time.perf_counter() - t0))
    finally:
        venv.close()
        algo.stop()
    ratios = [t / o for o, t in zip(ours, theirs)]
    return dict(steps_per_env=n, ours=ours, rllib=theirs, ratios=ratios, ratio=float(np.median(ratios)))


def median_row(same: list[dict]) -> dict:
    """One configuration's row, every number the median over rounds."""
    out = dict(same[0])
    for k, v in same[0].items():
        if isinstance(v, (int, float)) and k not in ("runners", "envs_per_runner"):
            out[k] = float(np.median([r[k] for r in same]))
        elif isinstance(v, dict):
            out[k] = {kk: float(np.median([r[k][kk] for r in same])) for kk in v}
    return out


def two_vs_two(rows: list[dict]) -> float:
    """RLlib sampling with 2 runners x 1 env over our vector env with 2 workers (nan when not measured)."""
    ours = [r for r in rows if r["trainer"] == "agents.ppo" and r["runners"] == 2]
    theirs = [r for r in rows if r["trainer"] != "agents.ppo" and r["runners"] == 2 and r["envs_per_runner"] == 1]
    return theirs[0]["sampled"] / ours[0]["sampled"] if ours and theirs else float("nan")


def markdown(rows: list[dict], pair: dict) -> str:
    out = [
        "| trainer | env runners / workers | envs each | start-up (s) | sampled (steps/s) | trained (steps/s) "
        "| RSS per runner (MB) | per step: env / inference / connectors / all (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p = r.get("per_step_ms")
        ps = f"{p['env_step']:.1f} / {p['inference']:.2f} / {p['connectors']:.2f} / {p['total']:.1f}" if p else "–"
        rss = f"{r['rss_mb_per_runner']:.0f}" if "rss_mb_per_runner" in r else "–"
        out.append(
            f"| {r['trainer']} | {r['runners']} | {r['envs_per_runner']} | {r['startup_s']:.1f} | "
            f"{r['sampled']:.0f} | {r['trained']:.0f} | {rss} | {ps} |"
        )
    ours = ", ".join(f"{v:.0f}" for v in pair["ours"])
    theirs = ", ".join(f"{v:.0f}" for v in pair["rllib"])
    out.append(
        f"\n**Target** (RLlib sampling with 2 env runners >= 0.8x our vector env with 2 workers), measured in "
        f"alternating turns of {pair['steps_per_env']} steps per env, both kept running: ours {ours} steps/s, RLlib "
        f"{theirs} steps/s; ratio **{pair['ratio']:.2f}x** (median of {', '.join(f'{r:.2f}' for r in pair['ratios'])})."
    )
    return "\n".join(out)


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before Ray or an env starts (``benchmarks.lib.cli`` makes
    it one line and exit status 2): --render-only with a JSON that is not there, a size or count below 1."""
    if args.render_only:
        rendered_from(args.json, "--json")
        return
    for flag in ("steps", "iterations", "batch", "rounds", "paired_steps", "paired_rounds"):
        value = getattr(args, flag)
        if value < 1:
            raise ValueError(f"--{flag.replace('_', '-')} {value}: expected 1 or more")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        update_results(args.json)
        return json.loads(args.json.read_text())
    import ray

    from agents.rllib.env import register
    from agents.rllib.train import Args as RArgs
    from agents.rllib.train import init_ray

    if args.quick:
        args.steps, args.iterations, args.batch, args.rounds = 100, 1, 100, 1
        args.paired_steps, args.paired_rounds = 50, 1
    grid = [(0, 1), (1, 1)] if args.quick else [(0, 1), (0, 2), (1, 1), (1, 2), (2, 1), (2, 2)]
    workers = [1] if args.quick else [1, 2]
    t0 = time.time()
    rounds = []
    for _ in range(args.rounds):
        rows = [ours(w, args) for w in workers]
        init_ray(RArgs(num_env_runners=2))
        register()
        rows += [rllib(r, e, args) for r, e in grid]
        ray.shutdown()
        rounds.append(rows)
    rows = [median_row([rnd[i] for rnd in rounds]) for i in range(len(rounds[0]))]
    init_ray(RArgs(num_env_runners=2))
    register()
    pair = paired(args)
    ray.shutdown()
    ratio = pair["ratio"]
    report = dict(
        command="python -m benchmarks.rllib_speed " + " ".join(sys.argv[1:]),
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        machine=f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs",
        versions={m: __import__(m).__version__ for m in ("ray", "gymnasium", "torch", "mani_skill")},
        wall_min=(time.time() - t0) / 60,
        ratio_2_runners_vs_2_workers=ratio,
        paired=pair,
        grid_ratio_each_round=[two_vs_two(rnd) for rnd in rounds],
        rows=rows,
        rounds=rounds,
    )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    table = markdown(rows, pair)
    print(table)
    if args.update_results:
        update_results(args.json)
    return report


def section(report: dict, json_path: Path) -> str:
    """This benchmark's section of RESULTS.md, from its JSON (at ``json_path``, which it links) alone."""
    v = report["versions"]
    table = markdown(report["rows"], report["paired"])
    return (
        f"{HEAD}\n\nCommand: `{report['command']}` ({report['date']}, {report['machine']}; ray {v['ray']}, "
        f"gymnasium {v['gymnasium']}, torch {v['torch']}, mani_skill {v['mani_skill']}; {report['wall_min']:.1f} min). "
        "State observations, PPO, random initial weights; *sampled* = every runner's `sample()` in parallel, "
        "*trained* = whole training iterations (sampling + update) after a warm-up iteration. Raw data: "
        f"{raw_link(json_path)}.\n\n"
        f"{table}\n\n"
    )


def update_results(json_path: Path, results: Path = RESULTS) -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path``."""
    replace_section(results, HEAD, section(json.loads(json_path.read_text()), json_path))


if __name__ == "__main__":
    entry("benchmarks.rllib_speed", Args, main, check)
