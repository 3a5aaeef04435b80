"""The camera learner's update: one minibatch of the camera DAgger recipe, timed on real frames.

The camera recipe's wall clock is mostly its updates (``train_round``: DrQ shift, keypoint encoder, BC and
auxiliary losses, backward, AdamW). This times ``agents.dagger.train_round`` itself on frames the expert
recorded, in three configurations run in interleaved rounds so the ratios come from the same minutes:

1. ``fp32, pad+crop shift``: the DrQ shift as it was written before (float copy, replicate pad, two gathers,
   back to uint8/int16), kept here as the reference;
2. ``fp32``: the trainer's default;
3. ``bf16 encoder``: ``--precision bf16`` (only where the CPU has native bf16; otherwise left out).

    python -m benchmarks.learner_speed                     # ~2 min on 2 cores
    python -m benchmarks.learner_speed --quick --json /tmp/l.json
    python -m benchmarks.learner_speed --update-results    # also rewrites its section of RESULTS.md
    python -m benchmarks.learner_speed --render-only       # rewrites the section from --json, measuring nothing
    python -m benchmarks.learner_speed --device cuda --json /tmp/g.json   # on a GPU (RESULTS.md's GPU section)

A GPU run's table, beside the same machine's ``--device cpu`` run, is RESULTS.md's GPU section, which
``benchmarks/gpu_acceptance.py --render-only`` renders (its ``LEARNER_JSONS``); this script's section holds CPU
figures only.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
import tyro

from benchmarks.lib.cli import entry, rendered_from
from benchmarks.lib.report import RESULTS, raw_link, replace_section

ROOT = Path(__file__).resolve().parents[1]

HEAD = "## Camera learner update — `benchmarks/learner_speed.py`"
RECIPE = (
    "--obs rgbd --action-frame tool --encoder keypoints --aux-weight 1 --initial-updates 2000 --batch-size 64 "
    "--updates-per-round 500"
)


@dataclass
class Args:
    updates: int = 40
    """timed updates per configuration and round (after 5 untimed ones)"""
    rounds: int = 3
    """interleaved rounds; the table shows each configuration's median"""
    episodes: int = 4
    """expert episodes recorded as the dataset"""
    quick: bool = False
    """tiny sizes: checks the script runs and writes well-formed JSON"""
    json: Path = ROOT / "benchmarks" / "results" / "learner_speed.json"
    update_results: bool = False
    """rewrite this benchmark's section of benchmarks/RESULTS.md (CPU figures only)"""
    render_only: bool = False
    """measure nothing: rewrite the section of benchmarks/RESULTS.md from the JSON at --json"""
    device: str = "cpu"
    """where the updates run (``cuda``: the frames are recorded on the CPU envs as always, then the network,
    its optimiser and each minibatch live on the GPU)"""


def pad_crop_shift(obs: dict[str, torch.Tensor], pad: int = 4) -> dict[str, torch.Tensor]:
    """The reference: DrQ's shift as ``random_shift`` did it before (a float copy, replicate padding, two gathers)."""
    rgb, depth = obs["rgb"], obs["depth"]
    n, h, w, _ = rgb.shape
    img = torch.cat([rgb.float(), depth.float()], dim=-1).permute(0, 3, 1, 2)
    img = F.pad(img, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (n,), device=rgb.device)
    dy = torch.randint(0, 2 * pad + 1, (n,), device=rgb.device)
    rows = (dy[:, None] + torch.arange(h, device=rgb.device)[None]).view(n, 1, h, 1)
    cols = (dx[:, None] + torch.arange(w, device=rgb.device)[None]).view(n, 1, 1, w)
    c = img.shape[1]
    out = img.gather(2, rows.expand(n, c, h, img.shape[3])).gather(3, cols.expand(n, c, h, w)).permute(0, 2, 3, 1)
    return dict(obs, rgb=out[..., :3].to(rgb.dtype), depth=out[..., 3:].to(depth.dtype))


def record(args: Args):
    """The recipe's envs (one, in this process) and a dataset of noisy expert episodes, as round 0 records it."""
    import agents.dagger as dagger
    from agents.common import Dataset, train_seed

    cli = tyro.cli(dagger.Args, args=RECIPE.split() + ["--num-envs", "1", "--backend", "cpu"])
    envs = dagger.make_envs(cli, 1)
    policy = dagger.policy_for(envs.single_observation_space, 5, torch.device("cpu"), cli.encoder)
    o, info = envs.reset(seed=train_seed(1, 0))
    state = dagger.labels(o, info)
    data = Dataset(100_000)
    dagger.collect(envs, state, policy, data, args.episodes, 1.0, cli.dart_noise, torch.device("cpu"))
    envs.close()
    policy.norm.fit(data.obs["state"][: data.size])
    return cli, policy, data


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any env (``benchmarks.lib.cli`` makes it one line
    and exit status 2): --render-only with a JSON that is not there, a --device torch does not know or without CUDA
    here, a GPU run's --update-results (the section holds CPU figures), --updates, --rounds or --episodes below 1."""
    if args.render_only:
        rendered_from(args.json, "--json")
        return
    try:
        dev = torch.device(args.device)
    except RuntimeError as e:
        raise ValueError(f"--device {args.device!r}: {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {args.device}: torch.cuda.is_available() is False here")
    if dev.type != "cpu" and args.update_results:
        raise ValueError(
            "--update-results writes the CPU section of RESULTS.md; a GPU run's JSON goes into its GPU section "
            "(benchmarks/gpu_acceptance.py's LEARNER_JSONS, then gpu_acceptance.py --render-only)"
        )
    for flag, value in (("--updates", args.updates), ("--rounds", args.rounds), ("--episodes", args.episodes)):
        if value < 1:
            raise ValueError(f"{flag} {value}: expected 1 or more")


def main(args: Args) -> dict:
    check(args)
    if args.render_only:
        update_results(args.json)
        return json.loads(args.json.read_text())
    import agents.dagger as dagger
    from agents.common.precision import native_bf16

    dev = torch.device(args.device)
    if args.quick:
        args.updates, args.rounds, args.episodes = 3, 1, 1
    t0 = time.time()
    cli, policy, data = record(args)
    policy.to(dev)
    aux_head = dagger.aux_head_for(policy, dev)
    opt = torch.optim.AdamW(list(policy.parameters()) + list(aux_head.parameters()), lr=cli.learning_rate)
    configs = {"fp32, pad+crop shift": ("fp32", pad_crop_shift), "fp32": ("fp32", None)}
    if native_bf16(dev):
        configs["bf16 encoder"] = ("bf16", None)
    shift = dagger.random_shift
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def timed(precision: str, ref_shift, n: int) -> float:
        dagger.random_shift = ref_shift or shift
        try:
            sync()
            t = time.perf_counter()
            dagger.train_round(policy, opt, data, cli, dev, aux_head=aux_head, updates=n, precision=precision)
            sync()
            return (time.perf_counter() - t) / n
        finally:
            dagger.random_shift = shift

    per_round: dict[str, list[float]] = {k: [] for k in configs}
    for _ in range(args.rounds):
        for name, (precision, ref_shift) in configs.items():
            timed(precision, ref_shift, 5)
            per_round[name].append(timed(precision, ref_shift, args.updates))
    ref = statistics.median(per_round["fp32, pad+crop shift"])
    rows = []
    for name, times in per_round.items():
        med = statistics.median(times)
        rows.append(dict(config=name, ms=1e3 * med, rounds_ms=[1e3 * x for x in times], speedup=ref / med))
    report = dict(
        command="python -m benchmarks.learner_speed " + " ".join(sys.argv[1:]),
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        machine=f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, {torch.get_num_threads()} threads",
        device=torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
        versions={"torch": torch.__version__},
        recipe=RECIPE,
        dataset=data.size,
        wall_min=(time.time() - t0) / 60,
        rows=rows,
    )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    table = markdown(rows)
    print(table)
    if args.update_results:
        update_results(args.json)
    return report


def markdown(rows: list[dict]) -> str:
    lines = [
        "| configuration | ms per update (median) | rounds (ms) | speed-up vs the first row |",
        "|---|---|---|---|",
    ]
    for r in rows:
        each = ", ".join(f"{x:.1f}" for x in r["rounds_ms"])
        lines.append(f"| {r['config']} | {r['ms']:.1f} | {each} | {r['speedup']:.2f}x |")
    return "\n".join(lines)


def section(report: dict, json_path: Path) -> str:
    """This benchmark's section of RESULTS.md, from its JSON (at ``json_path``, which it links) alone."""
    if report.get("device", "cpu") != "cpu":
        raise ValueError(f"the section holds CPU figures; this JSON's are {report['device']}'s (RESULTS.md, GPU)")
    table = markdown(report["rows"])
    return (
        f"{HEAD}\n\nCommand: `{report['command']}` ({report['date']}, {report['machine']}; torch "
        f"{report['versions']['torch']}; {report['wall_min']:.1f} min). One update of the camera DAgger recipe "
        f"(`{report['recipe']}`): `agents.dagger.train_round` on {report['dataset']} frames the noisy expert "
        "recorded, the configurations in interleaved rounds. Raw data: "
        f"{raw_link(json_path)}.\n\n"
        f"{table}\n\n"
    )


def update_results(json_path: Path, results: Path = RESULTS) -> None:
    """Rewrite this benchmark's section of ``results`` from the JSON at ``json_path``."""
    replace_section(results, HEAD, section(json.loads(json_path.read_text()), json_path))


if __name__ == "__main__":
    entry("benchmarks.learner_speed", Args, main, check)
