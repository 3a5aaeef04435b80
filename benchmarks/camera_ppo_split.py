"""Where a PPO training step from the camera goes: the ``ppo-rgbd`` recipe timed phase by phase.

PPO from the hand camera trains at a fraction of the speed its envs step alone, so something besides the simulator
sets its pace. This runs the recipe's own pieces (``agents.ppo``'s ``make_envs``, ``agent_for``, ``Rollout`` and
``ppo_update``, with the recipe's envs, rollout length, minibatches and epochs) for a fixed number of env steps after
one warm-up iteration, and times the phases by wrapping methods of the instances, so the code timed is the
trainer's own and not a copy of its loop:

- collection: ``envs.step`` (the env, rendering included), the policy's forward passes (``get_action_and_value``
  and ``get_value`` under ``no_grad``), and the rest of the rollout (copies into the rollout storage, episode
  bookkeeping, GAE): the collection's total minus those two;
- the update: the forward passes (``get_action_and_value``), ``loss.backward`` (``torch.Tensor.backward``, wrapped
  for the update only), the optimiser (``step`` and ``zero_grad``), and the rest (loss arithmetic, the gradient-norm
  clip, minibatch gathering, the running observation normaliser's update): the update's total minus those three.

Configurations of the recipe (CONFIGS: ``today``, the recipe as it is; ``fast`` and ``fastest``, the update's
levers that measured to pay; ``keypoints`` and ``fast+keypoints``, the same with ``--encoder keypoints``, asked
for by name) train side by side in the same run, each its own envs, agent and optimiser from the
same seed, one iteration each in a rotating order per round, so each one's ratio to the envs alone comes from the
same minutes as the others'. The ``--overlap`` configurations run agents.ppo's ``Collector`` as the trainer does:
the next rollout is collected in a thread while the update runs, and each timed iteration ends once it is in
(nothing runs on into the next configuration's turn); their phases are not split (the two threads' times overlap),
only collection (the thread's own seconds), the update and the wait for the collection. Each also gets an overlap
bound: the speed if collection and the update ran side by side with nothing shared, the slower of the two setting
the pace; what overlapping them (workers rendering the next rollout while the learner updates) could pay at most,
before the two contend for the same cores.

Rendering cannot be separated by wrapping (the env's workers render), so after every training iteration the same
env configuration (the recipe's envs and wrappers, a separate instance) steps alone with seeded random actions, once
from rgbd and once from state; rendering's cost per env step is about the difference. Training, rgbd and state take
turns, so the drift of a shared machine lands on all three and the ratios come from the same minutes.

    python -m benchmarks.camera_ppo_split                    # 10240 env steps a configuration, ~15 min on 2 cores,
                                                             # far more when shared
    python -m benchmarks.camera_ppo_split --configs today fast
    python -m benchmarks.camera_ppo_split --no-probe-threads # without the thread probe below, on a shared machine
                                                             # the run's slowest part (half its wall clock and more)
    python -m benchmarks.camera_ppo_split --quick --json /tmp/c.json
    python -m benchmarks.camera_ppo_split --update-results   # also rewrites its section of RESULTS.md
    python -m benchmarks.camera_ppo_split --render-only      # rewrites the section from --json, measuring nothing

A probe beside the training (not counted in its time) reruns each iteration's update on a copy of the agent and
optimiser with all the machine's torch threads, since the trainer runs its update on the one thread it keeps beside
its env workers (``agents.common.one_thread_beside_workers``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from benchmarks.lib.cli import entry
from benchmarks.lib.report import RESULTS, argv_command, raw_link, recorded_command, replace_section

ROOT = Path(__file__).resolve().parents[1]

HEAD = "## Camera PPO step split — `benchmarks/camera_ppo_split.py`"
RECIPE = "ppo-rgbd"
RESULTS_JSON = ROOT / "benchmarks" / "results" / "camera_ppo_split.json"
# (key, label, how it is measured); the leaves sum to the iteration's time
PHASES = (
    ("collect_env", "collection: env step (`envs.step`)", "measured"),
    ("collect_forward", "collection: policy forward (`get_action_and_value`, `get_value`)", "measured"),
    ("collect_data", "collection: data movement and bookkeeping (storage, `obs_to`, episodes, GAE)", "remainder"),
    ("update_forward", "update: forward (`get_action_and_value`)", "measured"),
    ("update_backward", "update: backward (`Tensor.backward`)", "measured"),
    ("update_optimizer", "update: optimiser (`step`, `zero_grad`)", "measured"),
    ("update_rest", "update: loss arithmetic, grad-norm clip, minibatch gathering, obs normaliser", "remainder"),
    ("loop", "the loop around them", "remainder"),
)


CONFIGS: dict[str, tuple[tuple[str, ...], str]] = {
    "today": ((), "the recipe as it is"),
    "fast": (
        ("--precision", "auto", "--update-epochs", "4", "--num-minibatches", "4"),
        "bf16 encoder in the update, 4 epochs of 4 minibatches (128 rows)",
    ),
    "fastest": (
        ("--precision", "auto", "--update-epochs", "2", "--num-minibatches", "4"),
        "bf16 encoder in the update, 2 epochs of 4 minibatches (128 rows)",
    ),
    "keypoints": (("--encoder", "keypoints"), "the recipe with the keypoint encoder (KeypointCNN) for the Nature CNN"),
    "fast+keypoints": (
        ("--precision", "auto", "--update-epochs", "4", "--num-minibatches", "4", "--encoder", "keypoints"),
        "fast with the keypoint encoder (KeypointCNN) for the Nature CNN",
    ),
    "overlap": (("--overlap",), "the recipe, the next rollout collected in a thread while the update runs"),
    "fast+overlap": (
        ("--precision", "auto", "--update-epochs", "4", "--num-minibatches", "4", "--overlap"),
        "fast, the next rollout collected in a thread while the update runs",
    ),
}
"""training configurations compared in one run: the ``ppo-rgbd`` recipe's flags, then these (``--precision auto``
is bf16 on a CPU with native bf16, fp32 elsewhere; the JSON records which)"""
DEFAULT_CONFIGS = ("today", "fast", "fastest", "overlap", "fast+overlap")
"""what a run compares unless ``--configs`` says otherwise (the encoder's configurations are asked for by name)"""


@dataclass
class Args:
    env_steps: int = 10240
    """timed env steps of PPO training, rounded up to whole iterations (the recipe's 4 envs x 128 steps each),
    after one warm-up iteration"""
    seed: int = 1
    """seeds torch, the training envs and the random actions of the env-only measurements"""
    quick: bool = False
    """tiny sizes (2 envs x 16 steps, one epoch, one timed iteration): checks the script runs and writes its JSON"""
    probe_threads: bool = True
    """rerun each update on a copy with all the machine's torch threads (not counted in training's time)"""
    configs: tuple[str, ...] = DEFAULT_CONFIGS
    """the training configurations to compare (CONFIGS), each its own envs, agent and optimiser, iterations in
    turns; the first is the one whose split the section details"""
    json: Path = RESULTS_JSON
    update_results: bool = False
    """rewrite this benchmark's section of benchmarks/RESULTS.md"""
    render_only: bool = False
    """measure nothing: rewrite the section of benchmarks/RESULTS.md from the JSON at --json"""


class Timers:
    """Seconds spent in wrapped methods, summed per key; ``phase`` prefixes the key, so one method (the agent's
    forward) counts apart in collection and in the update."""

    def __init__(self) -> None:
        self.acc: dict[str, float] = {}
        self.phase = "collect"
        self.calls: dict[str, int] = {}

    def add(self, key: str, seconds: float) -> None:
        key = f"{self.phase}_{key}"
        self.acc[key] = self.acc.get(key, 0.0) + seconds
        self.calls[key] = self.calls.get(key, 0) + 1

    def wrap(self, obj, name: str, key: str) -> None:
        """Replace ``obj.name`` by a timed call of the original (an instance attribute: other instances keep
        theirs)."""
        original = getattr(obj, name)

        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return original(*a, **k)
            finally:
                self.add(key, time.perf_counter() - t)

        setattr(obj, name, timed)

    def reset(self) -> dict[str, float]:
        out, self.acc, self.calls = self.acc, {}, {}
        return out


class timed_backward:
    """``torch.Tensor.backward`` timed into ``timers`` while the block runs (the loss is made inside
    ``ppo_update``, so the class's method is the one place to catch it), restored after."""

    def __init__(self, timers: Timers) -> None:
        self.timers = timers

    def __enter__(self):
        self.original = original = torch.Tensor.backward
        timers = self.timers

        def backward(tensor, *a, **k):
            t = time.perf_counter()
            try:
                return original(tensor, *a, **k)
            finally:
                timers.add("backward", time.perf_counter() - t)

        torch.Tensor.backward = backward
        return self

    def __exit__(self, *exc) -> None:
        torch.Tensor.backward = self.original


def recipe_args(quick: bool, seed: int, config: str = "today"):
    """The ``ppo-rgbd`` recipe's ``agents.ppo.Args`` on this machine's CPU with ``config``'s flags (``--quick``:
    2 envs x 16 steps, one epoch of 2 minibatches, whatever the configuration says)."""
    import agents.ppo as ppo
    from agents.common import cli

    argv = ["--recipe", RECIPE, "--seed", str(seed), "--backend", "cpu", "--device", "cpu", "--no-progress"]
    argv += list(CONFIGS[config][0])
    if quick:
        argv += ["--num-envs", "2", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1"]
    return cli(ppo.Args, "agents.ppo", argv), argv


def env_only(envs, steps: int, rng: np.random.Generator) -> float:
    """Env steps/s of ``steps`` batched steps of uniform random actions (the envs auto-reset finished episodes)."""
    space = envs.single_action_space
    acts = rng.uniform(space.low, space.high, size=(steps, envs.num_envs, *space.shape)).astype(np.float32)
    t = time.perf_counter()
    for a in acts:
        envs.step(torch.from_numpy(a))
    return steps * envs.num_envs / (time.perf_counter() - t)


def update_probe(agent, optimizer, batch: dict, args, make_agent: Callable, threads: int) -> tuple[float, int]:
    """Seconds and optimiser steps of ``ppo_update`` on ``batch`` for a copy of ``agent`` and ``optimizer`` at
    ``threads`` torch threads; the training's own agent is untouched."""
    import agents.ppo as ppo
    from agents.common import torch_threads

    copy = make_agent()
    copy.load_state_dict(agent.state_dict())
    opt = torch.optim.Adam(copy.parameters(), lr=args.learning_rate, eps=1e-5)
    opt.load_state_dict(optimizer.state_dict())
    steps = [0]
    step = opt.step

    def counted(*a, **k):
        steps[0] += 1
        return step(*a, **k)

    opt.step = counted
    copy.train()
    rng = torch.get_rng_state()
    with torch_threads(threads):
        t = time.perf_counter()
        ppo.ppo_update(copy, opt, batch, args)
        seconds = time.perf_counter() - t
    torch.set_rng_state(rng)  # the training's minibatch permutations stay what they would have been
    return seconds, steps[0]


class Trainer:
    """One configuration's training: its own envs, agent, optimiser and rollout (``agents.ppo``'s own pieces),
    its methods wrapped into its own timers."""

    def __init__(self, config: str, args: Args) -> None:
        import agents.ppo as ppo
        from agents.common import flatten_obs, obs_to
        from agents.common.precision import resolve_precision

        self.config = config
        self.cli, self.argv = recipe_args(args.quick, args.seed, config)
        cli, device = self.cli, torch.device("cpu")
        self.precision = resolve_precision(cli.precision, device)
        torch.manual_seed(cli.seed)  # every configuration starts from the same weights
        self.envs = ppo.make_envs(cli, cli.num_envs)  # training's: this process on one torch thread beside workers
        self.agent = ppo.agent_for(self.envs, device, cli)
        self.optimizer = torch.optim.Adam(self.agent.parameters(), lr=cli.learning_rate, eps=1e-5)  # as train()
        next_obs, _ = self.envs.reset(seed=cli.seed)
        self.rollout = ppo.Rollout(self.envs, obs_to(flatten_obs(next_obs), device), cli, device, cli.overlap)
        self.timers = timers = Timers()
        self.collector = None
        if cli.overlap:  # the trainer's own Collector, made before any method is wrapped (it copies the agent)
            self.collector = ppo.Collector(self.rollout, self.agent, cli.seed)
        else:  # the phases of the collection, timed in the one thread
            timers.wrap(self.envs, "step", "env")
            timers.wrap(self.agent, "get_action_and_value", "forward")
            timers.wrap(self.agent, "get_value", "forward")
        timers.wrap(self.optimizer, "step", "optimizer")
        timers.wrap(self.optimizer, "zero_grad", "optimizer")
        self.rounds: list[dict] = []

    def iteration(self) -> tuple[dict, dict]:
        """One PPO iteration as ``agents.ppo.train`` runs it, timed: (the row, the rollout's batch)."""
        import agents.ppo as ppo

        cli, agent, timers = self.cli, self.agent, self.timers
        if self.collector is not None:
            return self.overlapped_iteration()
        recent: dict[str, list[float]] = defaultdict(list)
        timers.reset()
        timers.phase = "collect"
        t0 = time.perf_counter()
        batch, _ = self.rollout.collect(agent, recent)
        t1 = time.perf_counter()
        agent.train()
        timers.phase = "update"
        t2 = time.perf_counter()
        with timed_backward(timers):
            ppo.ppo_update(agent, self.optimizer, batch, cli)
        if agent.norm is not None:  # as agents.ppo.train does after each update
            agent.norm.update(batch["obs"]["state"])
        t3 = time.perf_counter()
        acc, calls = timers.acc, timers.calls
        timers.reset()
        row = dict(
            wall_s=t3 - t0,
            env_steps=cli.batch_size,
            collect_s=t1 - t0,
            update_s=t3 - t2,
            loop_s=t2 - t1,
            optimizer_steps=calls.get("update_optimizer", 0) // 2,  # step and zero_grad each count once
            **{f"{k}_s": v for k, v in acc.items()},
        )
        return row, batch

    def overlapped_iteration(self) -> tuple[dict, dict]:
        """One ``--overlap`` iteration as ``agents.ppo.PPO.step`` runs it: the rollout collected during the last
        update (the warm-up's collected now), the next one launched in the thread, the update, the wait for it."""
        import agents.ppo as ppo

        cli, agent, timers, collector = self.cli, self.agent, self.timers, self.collector
        timers.reset()
        timers.phase = "update"  # only the optimiser is wrapped, and only the learner's thread calls it
        t0 = time.perf_counter()
        batch, _, _, collect_s = collector.take(agent)
        collector.launch(agent)
        t1 = time.perf_counter()
        agent.train()
        ppo.ppo_update(agent, self.optimizer, batch, cli)
        if agent.norm is not None:
            agent.norm.update(batch["obs"]["state"])
        t2 = time.perf_counter()
        collector.join()
        t3 = time.perf_counter()
        calls = timers.calls
        timers.reset()
        row = dict(
            wall_s=t3 - t0,
            env_steps=cli.batch_size,
            collect_s=collector.ready[3],  # the thread's seconds for the rollout it collected beside this update
            update_s=t2 - t1,
            loop_s=0.0,
            wait_s=(t1 - t0) + (t3 - t2),
            optimizer_steps=calls.get("update_optimizer", 0) // 2,
        )
        return row, batch

    def close(self) -> None:
        if self.collector is not None:
            self.collector.close()
        self.envs.close()


def measure(args: Args) -> dict:
    """Build each configuration's training (:class:`Trainer`) and two env-only copies of the recipe's envs (rgbd,
    state), then take turns: one PPO iteration of each configuration, the rgbd envs alone, the state envs alone,
    for the iterations asked; the order within a round rotates, so no configuration always runs first."""
    import agents.ppo as ppo

    t_start = time.time()
    load_start = os.getloadavg()
    trainers: list[Trainer] = []
    alone: dict = {}
    try:
        for config in args.configs:
            trainers.append(Trainer(config, args))
        cli = trainers[0].cli
        iterations = max(1, math.ceil((1 if args.quick else args.env_steps) / cli.batch_size))
        alone = {
            "rgbd": ppo.make_envs(cli, cli.num_envs),
            "state": ppo.make_envs(replace(cli, obs="state"), cli.num_envs),
        }
        threads = torch.get_num_threads()
        rng = np.random.default_rng(args.seed)
        for e in alone.values():
            e.reset(seed=cli.seed + 1000)
            env_only(e, 5, rng)  # warm-up: the first steps fill caches
        first = trainers[0]
        probe = args.probe_threads and (os.cpu_count() or 1) > threads
        make_agent = lambda: ppo.agent_for(first.envs, torch.device("cpu"), first.cli)  # noqa: E731
        env_rounds = []
        t_loop = time.time()
        for i in range(iterations + 1):  # iteration 0 warms up, untimed
            k = i % len(trainers)
            rows = {}
            for trainer in trainers[k:] + trainers[:k]:
                row, batch = trainer.iteration()
                row["iteration"] = i
                if probe and trainer is first:  # not counted in its time; its threads end before the next phase
                    seconds, steps = update_probe(first.agent, first.optimizer, batch, first.cli, make_agent,
                                                  os.cpu_count())  # fmt: skip
                    row.update(probe_update_s=seconds, probe_optimizer_steps=steps)
                rows[trainer.config] = row
            env_row = dict(iteration=i)
            for name in list(alone) if i % 2 else list(alone)[::-1]:  # each first in every other round
                env_row[f"{name}_env_steps_per_s"] = env_only(alone[name], cli.num_steps, rng)
            env_row["loadavg_1min"] = os.getloadavg()[0]
            if i > 0:
                env_rounds.append(env_row)
                for trainer in trainers:
                    trainer.rounds.append({**rows[trainer.config], **env_row})
            per_round = (time.time() - t_loop) / (i + 1)
            done = sum(r["env_steps"] for r in first.rounds)
            speeds = ", ".join(f"{c} {r['env_steps'] / r['wall_s']:.0f}" for c, r in rows.items())
            print(
                f"[{'warm-up' if i == 0 else f'{i}/{iterations}'}] {done}/{iterations * cli.batch_size} env steps "
                f"each; training env steps/s: {speeds}; alone rgbd {env_row['rgbd_env_steps_per_s']:.0f} state "
                f"{env_row['state_env_steps_per_s']:.0f}; ETA {per_round * (iterations - i):.0f} s",
                file=sys.stderr,
                flush=True,
            )
    finally:
        for t in trainers:
            t.close()
        for e in alone.values():
            e.close()
    return summarize(trainers, threads, t_start, load_start)


def config_summary(rounds: list[dict], alone_rgbd: float) -> dict:
    """One configuration's timed iterations as rates and milliseconds per env step; the overlap bound is the
    speed if collection and the update ran side by side with nothing shared (the slower of the two sets the
    pace), an upper bound on what overlapping them could pay."""
    steps = sum(r["env_steps"] for r in rounds)
    total = lambda key: sum(r.get(key, 0.0) for r in rounds)  # noqa: E731
    ms = lambda seconds: 1e3 * seconds / steps  # noqa: E731
    split = dict(
        collect_env=ms(total("collect_env_s")),
        collect_forward=ms(total("collect_forward_s")),
        update_forward=ms(total("update_forward_s")),
        update_backward=ms(total("update_backward_s")),
        update_optimizer=ms(total("update_optimizer_s")),
        loop=ms(total("loop_s")),
    )
    split["collect_data"] = ms(total("collect_s")) - split["collect_env"] - split["collect_forward"]
    split["update_rest"] = (
        ms(total("update_s")) - split["update_forward"] - split["update_backward"] - split["update_optimizer"]
    )
    training = steps / total("wall_s")
    per_round = sorted(r["env_steps"] / r["wall_s"] / r["rgbd_env_steps_per_s"] for r in rounds)
    bound = 1e3 / max(ms(total("collect_s")), ms(total("update_s") + total("loop_s")))
    waited = dict(wait_ms_per_env_step=ms(total("wait_s"))) if any("wait_s" in r for r in rounds) else {}
    return dict(
        env_steps=steps,
        training_env_steps_per_s=training,
        ratio_training_to_env_only_rgbd=training / alone_rgbd,
        ratio_rounds=dict(median=float(np.median(per_round)), min=per_round[0], max=per_round[-1]),
        total_ms_per_env_step=1e3 / training,
        collect_ms_per_env_step=ms(total("collect_s")),
        update_ms_per_env_step=ms(total("update_s")),
        overlap_bound_env_steps_per_s=bound,
        overlap_bound_ratio_to_env_only_rgbd=bound / alone_rgbd,
        split_ms_per_env_step=split,
        optimizer_steps_per_iteration=total("optimizer_steps") / len(rounds),
        **waited,
    )


def summarize(trainers: list, threads: int, t_start: float, load_start) -> dict:
    """The timed iterations' sums as rates and milliseconds per env step: the first configuration's at the top
    level (with its rounds), every configuration's under ``configs``."""
    first = trainers[0]
    rounds, cli = first.rounds, first.cli
    # env-only speeds: total steps over total time, each block the same number of env steps
    alone = {m: len(rounds) / sum(1 / r[f"{m}_env_steps_per_s"] for r in rounds) for m in ("rgbd", "state")}
    configs = {}
    for t in trainers:
        c = t.cli
        configs[t.config] = dict(
            description=CONFIGS[t.config][1],
            flags=list(CONFIGS[t.config][0]),
            precision=t.precision,
            num_minibatches=c.num_minibatches,
            update_epochs=c.update_epochs,
            **config_summary(t.rounds, alone["rgbd"]),
        )
    top = configs[first.config]
    render = [1e3 / r["rgbd_env_steps_per_s"] - 1e3 / r["state_env_steps_per_s"] for r in rounds]
    report = dict(
        command=argv_command("benchmarks.camera_ppo_split", sys.argv[1:]),
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        wall_min=(time.time() - t_start) / 60,
        machine=dict(
            node=platform.node(),
            arch=platform.machine(),
            cpus=os.cpu_count(),
            torch_threads_training=threads,
            loadavg_start=list(load_start),
            loadavg_end=list(os.getloadavg()),
        ),
        versions=dict(torch=torch.__version__, python=platform.python_version()),
        recipe=RECIPE,
        recipe_argv=first.argv,
        settings=dict(
            num_envs=cli.num_envs,
            num_steps=cli.num_steps,
            batch_size=cli.batch_size,
            num_minibatches=cli.num_minibatches,
            update_epochs=cli.update_epochs,
            target_kl=cli.target_kl,
            obs_norm=cli.obs_norm,
            backend=cli.backend,
        ),
        warmup_iterations=1,
        iterations=len(rounds),
        env_steps=top["env_steps"],
        training_env_steps_per_s=top["training_env_steps_per_s"],
        env_only_rgbd_env_steps_per_s=alone["rgbd"],
        env_only_state_env_steps_per_s=alone["state"],
        env_only_steps_per_round=cli.batch_size,
        ratio_training_to_env_only_rgbd=top["ratio_training_to_env_only_rgbd"],
        total_ms_per_env_step=top["total_ms_per_env_step"],
        rendering_ms_per_env_step=1e3 / alone["rgbd"] - 1e3 / alone["state"],
        rendering_ms_per_env_step_rounds=dict(
            median=float(np.median(render)), min=float(np.min(render)), max=float(np.max(render))
        ),
        env_only_rgbd_ms_per_env_step=1e3 / alone["rgbd"],
        split_ms_per_env_step=top["split_ms_per_env_step"],
        optimizer_steps_per_iteration=top["optimizer_steps_per_iteration"],
        configs=configs,
        rounds=rounds,
        config_rounds={t.config: t.rounds for t in trainers[1:]},
    )
    if all("probe_update_s" in r for r in rounds):
        total = lambda key: sum(r.get(key, 0.0) for r in rounds)  # noqa: E731
        report["update_probe"] = dict(
            threads=os.cpu_count(),
            ms_per_optimizer_step=1e3 * total("probe_update_s") / total("probe_optimizer_steps"),
            training_ms_per_optimizer_step=1e3 * total("update_s") / total("optimizer_steps"),
        )
    return report


def check(args: Args) -> None:
    """Refuse what cannot run, naming the flag, before any env (``benchmarks.lib.cli`` makes it one line and exit
    status 2)."""
    if args.env_steps < 1:
        raise ValueError(f"--env-steps must be >= 1, got {args.env_steps}")
    unknown = [c for c in args.configs if c not in CONFIGS]
    if unknown or not args.configs or len(set(args.configs)) != len(args.configs):
        raise ValueError(f"--configs must name distinct configurations of {tuple(CONFIGS)}, got {args.configs}")
    if args.render_only and not args.json.is_file():
        raise ValueError(f"--render-only reads --json {args.json}, which does not exist")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        update_results(args.json)
        return json.loads(args.json.read_text())
    report = measure(args)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    print(markdown(report))
    if args.update_results:
        update_results(args.json)
    return report


def markdown(r: dict) -> str:
    """The tables: each configuration's speed beside the envs alone, then the split of its time per env step
    (a column per configuration)."""
    configs = r.get("configs") or {"today": dict(r, flags=[], description="the recipe as it is")}
    rows = [
        "| measured in turns | flags after the recipe's | optimiser steps an iteration | env steps/s | "
        "ms per env step | / envs alone rgbd (rounds: median, range) | overlap bound |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, c in configs.items():
        rounds = c.get("ratio_rounds")
        spread = f" ({rounds['median']:.2f}, {rounds['min']:.2f}–{rounds['max']:.2f})" if rounds else ""
        flags = f"`{' '.join(c['flags'])}`" if c["flags"] else "—"
        if c.get("precision") and "--precision" in c["flags"]:
            flags += f" (= {c['precision']})"
        bound = c.get("overlap_bound_ratio_to_env_only_rgbd")
        if "wait_ms_per_env_step" in c:  # overlapped: what it is made of instead of a bound
            bound = None
            spread += (
                f" (overlapped: collection {c['collect_ms_per_env_step']:.2f},"
                f" update {c['update_ms_per_env_step']:.2f},"
                f" waiting for the collection {c['wait_ms_per_env_step']:.2f} ms per env step)"
            )
        rows.append(
            f"| PPO training from the camera, **{name}** | {flags} | {c['optimizer_steps_per_iteration']:.0f} | "
            f"**{c['training_env_steps_per_s']:.0f}** | {c['total_ms_per_env_step']:.2f} | "
            f"**{c['ratio_training_to_env_only_rgbd']:.2f}x**{spread} | "
            + (f"{c['overlap_bound_env_steps_per_s']:.0f} ({bound:.2f}x) |" if bound else "|")
        )
    configs = {n: c for n, c in configs.items() if "wait_ms_per_env_step" not in c}  # split: in one thread only
    rows += [
        f"| the same envs alone, rgbd | | | {r['env_only_rgbd_env_steps_per_s']:.0f} | "
        f"{r['env_only_rgbd_ms_per_env_step']:.2f} | 1 | |",
        f"| the same envs alone, state | | | {r['env_only_state_env_steps_per_s']:.0f} | "
        f"{1e3 / r['env_only_state_env_steps_per_s']:.2f} | | |",
        "",
        "| phase of a training iteration, ms per env step (share) | "
        + " | ".join(f"{name}" for name in configs)
        + " | how |",
        "|---|" + "---|" * len(configs) + "---|",
    ]
    if not configs:
        return "\n".join(rows[:-3])
    share = lambda ms, c: f"{ms:.2f} ({100 * ms / c['total_ms_per_env_step']:.0f} %)"  # noqa: E731
    for key, label, how in PHASES:
        cells = [share(c["split_ms_per_env_step"][key], c) for c in configs.values()]
        rows.append(f"| {label} | " + " | ".join(cells) + f" | {how} |")
        if key == "collect_env":
            render = r["rendering_ms_per_env_step"]
            first = next(iter(configs.values()))
            cell = (
                f"{render:.2f} ({100 * render / first['total_ms_per_env_step']:.0f} %)"
                if render > 0
                else "not resolved"
            )
            rows.append(
                f"| … of which rendering (envs alone: rgbd − state) | {cell} |"
                + " |" * (len(configs) - 1)
                + " difference |"
            )
    cells = [f"**{c['total_ms_per_env_step']:.2f}**" for c in configs.values()]
    rows.append("| **total** (1000 / training env steps/s) | " + " | ".join(cells) + " | |")
    return "\n".join(rows)


def reading(r: dict) -> str:
    """Which phase dominates, in words, from the numbers alone."""
    split, total = r["split_ms_per_env_step"], r["total_ms_per_env_step"]
    labels = {k: label for k, label, _ in PHASES}
    top = max(split, key=split.get)
    update = sum(v for k, v in split.items() if k.startswith("update_"))
    collect = sum(v for k, v in split.items() if k.startswith("collect_"))
    text = (
        f"The largest phase is {labels[top].replace('`', '')} ({100 * split[top] / total:.0f} % of the time). "
        f"The update takes {100 * update / total:.0f} % ({update:.2f} ms per env step, "
        f"{r['optimizer_steps_per_iteration']:.0f} optimiser steps an iteration on average), collection "
        f"{100 * collect / total:.0f} %, and the env step itself {100 * split['collect_env'] / total:.0f} %."
    )
    rounds = r["rendering_ms_per_env_step_rounds"]
    slow = sum(x["state_env_steps_per_s"] <= x["rgbd_env_steps_per_s"] for x in r["rounds"])
    if r["rendering_ms_per_env_step"] > 0 and rounds["min"] > 0:
        share = 100 * r["rendering_ms_per_env_step"] / total
        text += f" Rendering (the envs alone, rgbd − state) is about {share:.0f} % of the time."
    else:
        text += (
            f" Rendering's share is not resolved in this run: in {slow} of {len(r['rounds'])} rounds the envs alone "
            f"ran no faster from state than from rgbd (rgbd − state ranged {rounds['min']:.2f} to "
            f"{rounds['max']:.2f} ms per env step over the rounds, median {rounds['median']:.2f})."
        )
    configs = r.get("configs") or {}
    names = list(configs)
    if len(names) > 1:
        base = configs[names[0]]
        faster = [
            f"{name} {c['training_env_steps_per_s'] / base['training_env_steps_per_s']:.2f}x as fast "
            f"({c['ratio_training_to_env_only_rgbd']:.2f} of the envs alone; update "
            f"{c['update_ms_per_env_step']:.2f} ms per env step against {base['update_ms_per_env_step']:.2f})"
            for name, c in configs.items()
            if name != names[0]
        ]
        text += f" Against {names[0]} in the same rounds: " + "; ".join(faster) + "."
        best = max(configs, key=lambda n: configs[n]["training_env_steps_per_s"])
        c = configs[best]
        text += (
            f" Collection (env, forward, storage) takes {c['collect_ms_per_env_step']:.2f} ms per env step in "
            f"{best}, so with the update overlapped with it (workers render the next rollout while the learner "
            f"updates) and nothing shared, {best} would run at most at {c['overlap_bound_env_steps_per_s']:.0f} env "
            f"steps/s ({c['overlap_bound_ratio_to_env_only_rgbd']:.2f} of the envs alone): the column overlap bound."
        )
    probe = r.get("update_probe")
    if probe:
        speedup = probe["training_ms_per_optimizer_step"] / probe["ms_per_optimizer_step"]
        text += (
            f" The trainer updates on {r['machine']['torch_threads_training']} torch thread; the same updates on a "
            f"copy with {probe['threads']} threads took {probe['ms_per_optimizer_step']:.0f} ms per optimiser step "
            f"against {probe['training_ms_per_optimizer_step']:.0f} ms ({speedup:.2f}x)."
        )
    return text


def section(report: dict, json_path: Path) -> str:
    """This benchmark's section of RESULTS.md, from its JSON (at ``json_path``, which it links) alone."""
    s, m = report["settings"], report["machine"]
    load = lambda xs: "/".join(f"{x:.1f}" for x in xs)  # noqa: E731
    configs = report.get("configs") or {}
    side = ""
    if len(configs) > 1:
        side = (
            " Its configurations train side by side ("
            + "; ".join(f"{name}: {c['description']}" for name, c in configs.items())
            + "), each with its own envs, agent and optimiser from the same seed, one iteration of each per round in "
            "a rotating order, the same env steps each. The overlap bound is a configuration's speed if collection "
            "and the update ran side by side with nothing shared (the slower of the two setting the pace)."
        )
    return (
        f"{HEAD}\n\nCommand: `{recorded_command(report['command'])}` ({report['date']}, {m['node']} {m['arch']}, "
        f"{m['cpus']} CPUs, torch {report['versions']['torch']} on {m['torch_threads_training']} thread in training; "
        f"{report['wall_min']:.1f} min; load average {load(m['loadavg_start'])} at the start, "
        f"{load(m['loadavg_end'])} at the end, on a machine shared with other work). The `{report['recipe']}` "
        f"recipe's PPO (`agents.ppo`'s own envs, rollout and update: {s['num_envs']} envs x {s['num_steps']} steps "
        f"an iteration, {s['update_epochs']} epochs of {s['num_minibatches']} minibatches, target KL "
        f"{s['target_kl']}) for {report['env_steps']} env steps ({report['iterations']} iterations after "
        f"{report['warmup_iterations']} warm-up), each iteration followed by the same envs stepped alone with random "
        f"actions, from rgbd and from state ({report['env_only_steps_per_round']} env steps each), so the ratios "
        "come from the same minutes. Phases are timed by wrapping the instances' methods; the rows marked "
        f"remainder are a total minus its measured parts.{side} Raw data: "
        f"{raw_link(json_path)}.\n\n"
        f"{markdown(report)}\n\n"
        f"{reading(report)}\n\n"
    )


def update_results(json_path: Path, results: Path = RESULTS) -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path``."""
    replace_section(results, HEAD, section(json.loads(json_path.read_text()), json_path))


if __name__ == "__main__":
    entry("benchmarks.camera_ppo_split", Args, main, check)
