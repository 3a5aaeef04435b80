"""The sim-vs-real table on the emulator's digital twin: ``sim2real-eval`` for one or more policies with no shift, each
shift alone, and all of them together. Prints a markdown table and, over all (policy, shift) cells, the agreement of
sim and twin success (MMRV and Pearson r, as SimplerEnv reports them) and, per cell, whether its sim/twin difference
is more than chance (the seeds won on one side only, McNemar's exact test); writes JSON (and each run's report under
``--out``). The sim side is put in each row's condition as well (``--no-sim-shift``: the nominal task throughout),
so a row says both what the sim predicts and what the twin does; a policy's target reads against its own no-shift
sim row. The camera-mount rows are run again with the frames corrected to the trained mount from the measured offset
(``sim2real-eval --camera-mount``), exact and off by 2 mm / 1 deg; their sim side keeps the trained mount. The
rows in MOUNT_ERRORS (the mount's offset scaled, or its position or rotation alone) run only when named: how far
from the trained mount a camera may sit before the policy fails.

    .venv/bin/python benchmarks/sim2real_gap.py --episodes 10 --json benchmarks/results/sim2real_gap.json
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT --camera none --shifts none "all together"
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT_A CKPT_B --camera twin --episodes 30
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT --camera twin --episodes 30 --workers 2
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT --shifts "lighting & colours/textures"   # combined
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT --camera twin --episodes 30 --reuse   # goes on
    .venv/bin/python benchmarks/sim2real_gap.py --policy CKPT --shifts none "camera mount x0.1" "camera mount x0.25"

``--workers N`` runs N cells at once, each in its own process with its own emulator (one torch thread each on a
2-core machine). A real step ends when the robot stands at its target, so a busy machine makes the cells
slower, not different; the round-trip column, a time, is then the loaded machine's.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import tyro

from maniskill_irb120.envs.randomization import Randomization
from maniskill_irb120.sim2real.eval import EvalConfig, evaluate, sim_side_shift
from maniskill_irb120.sim2real.policy import resolve_policy
from maniskill_irb120.sim2real.report import agreement, paired_gap

SHIFTS = {
    "none": None,
    "camera mount": "camera_pos=0.01;-0.01;0.005,camera_rot=3;-3;5",
    "field of view": "camera_fov=75",
    "lighting": "light=0.5",
    "colours/textures": "color=0.25,texture=1,roughness=0.3,specular=0.8",
    "depth noise + dropout": "depth_noise=4,depth_dropout=0.05",
    "depth model D435": "depth_model=d435",
    "object size/mass/friction": "object_size=1.2,object_mass=2,object_friction=0.5",
    "command latency 30 ms": "latency=0.03",
}
SHIFTS["all together"] = ",".join(v for v in SHIFTS.values() if v)
# the same mount, its frames reprojected to the trained mount (sim2real-eval --camera-mount) from what hand-eye
# calibration measured: exactly the offset, or the offset off by 2 mm and 1 degree per axis
MOUNTS = {
    "camera mount, corrected": SHIFTS["camera mount"],
    "camera mount, corrected with 2 mm / 1 deg error": "camera_pos=0.012;-0.012;0.007,camera_rot=4;-2;4",
    "all together, mount corrected": SHIFTS["camera mount"],
}
# the mount's offset in part: how far from the trained mount a camera may sit (a hand-eye calibration's error, once
# training uses the measured mount) before the policy fails; run by name only, not in the default table. For a policy
# trained at the "camera mount" row's mount, x0.75 and x1.25 put the camera a quarter of that offset off its own
MOUNT_ERRORS = {
    **{f"camera mount x{k:g}": (k, k) for k in (0.1, 0.25, 0.5, 0.75, 1.25)},
    "camera mount, position only": (1.0, 0.0),
    "camera mount, rotation only": (0.0, 1.0),
}


def scaled_mount(pos_scale: float, rot_scale: float) -> str:
    """The "camera mount" row's offset with its position and its rotation scaled (a part scaled to 0 left out)."""
    mount = Randomization.parse(SHIFTS["camera mount"])
    parts = dict(camera_pos=(pos_scale, mount.camera_pos), camera_rot=(rot_scale, mount.camera_rot))
    return ",".join(
        f"{key}={';'.join(f'{scale * v:.6g}' for v in values)}" for key, (scale, values) in parts.items() if scale
    )


SHIFTS.update({name: scaled_mount(*scales) for name, scales in MOUNT_ERRORS.items()})
SHIFTS["camera mount, corrected"] = SHIFTS["camera mount"]
SHIFTS["camera mount, corrected with 2 mm / 1 deg error"] = SHIFTS["camera mount"]
SHIFTS["all together, mount corrected"] = SHIFTS["all together"]
JOIN = "&"
"""--shifts "lighting & colours/textures": a row of several shifts at once (any of the plain rows above)"""


def spec_of(name: str) -> str | None:
    """The randomisation string of a row: one of SHIFTS, or plain rows joined by JOIN (which sinks a policy when
    "all together" does is a question of combinations)."""
    if name in SHIFTS:
        return SHIFTS[name]
    parts = [p.strip() for p in name.split(JOIN)]
    bad = [p for p in parts if p not in SHIFTS or p in MOUNTS or SHIFTS[p] is None]
    if JOIN not in name or bad:
        plain = [n for n in SHIFTS if n not in MOUNTS and SHIFTS[n] is not None]
        raise ValueError(
            f"--shifts {name!r}: the rows are {list(SHIFTS)}, or plain ones joined by '{JOIN}' (of {plain})"
        )
    return ",".join(SHIFTS[p] for p in parts)


@dataclass
class Args:
    policy: tuple[str, ...] = ("expert",)
    """'expert', checkpoints of agents.ppo, agents.dagger or agents.sac, or committed policies by file or by their
    short name in benchmarks/results/policies/MANIFEST.json; with several, every one runs every
    row and the sim/twin agreement (MMRV, Pearson r) is over all (policy, shift) cells"""
    camera: str = "twin"
    """twin (the twin's render) or none (a state policy: no frames rendered for it)"""
    shifts: tuple[str, ...] = ()
    """rows to run, by name (default: SHIFTS but MOUNT_ERRORS; without a camera, those of them that correct none)"""
    episodes: int = 10
    seed: int = 1000
    out: Path = Path("runs/sim2real_gap")
    json: Optional[Path] = None
    workers: int = 1
    """cells (policy x shift) run at once, each in its own process"""
    sim_shift: bool = True
    """put the sim side in each row's condition too (its own prediction, which the agreement compares with the
    twin's); --no-sim-shift: the nominal sim in every row"""
    reuse: bool = False
    """a cell whose folder under --out already holds a finished report of the same configuration (policy,
    episodes, seed, shift, camera) is read, not run again: a table that was stopped goes on where it stood"""


def folder(name: str) -> str:
    """A row's folder under --out."""
    return name.replace(" ", "_").replace("/", "_")


def cell(policy: str, name: str, args: Args) -> dict:
    """One (policy, shift) cell: ``sim2real-eval`` on the same seeds in the sim and on the shifted twin."""
    t0 = time.time()
    sub = folder(name)
    spec = spec_of(name)
    cfg = EvalConfig(
        policy=policy,
        camera=args.camera,
        episodes=args.episodes,
        seed=args.seed,
        shift=spec,
        sim_shift=args.sim_shift and spec is not None,
        camera_mount=MOUNTS.get(name),
        out=args.out / (sub if len(args.policy) == 1 else f"{_short(policy)}_{sub}"),
    )
    r = _finished_report(cfg) if args.reuse else None
    if r is None:
        r = evaluate(cfg)
    else:
        print(f"{name!r} of {_short(policy)}: read from {cfg.out / 'report.json'} (--reuse)", file=sys.stderr)
        t0 -= r["wall_clock_s"]
    return dict(
        policy=policy,
        shift=name,
        spec=spec,
        camera_mount=MOUNTS.get(name),
        sim_success=r["sim"]["success"],
        real_success=r["real"]["success"],
        real_grasp=r["real"]["grasped"],
        real_drop=r["real"]["dropped"],
        real_collision=r["real"]["collided"],
        tcp_dev_mean_mm=1000 * r["deviation"]["tcp_m"].get("mean", float("nan")),
        latency_p50_ms=r["command_latency_ms"].get("p50"),
        refused=r["refused"]["total"],
        late_steps=r["late_steps"],
        paired=paired_gap(r["per_episode"]),
        wall_s=time.time() - t0,
    )


def _finished_report(cfg: EvalConfig) -> dict | None:
    """The report a cell left in its folder, if it ran this very configuration to the end without an error
    (the folder it was written to may have been moved since: ``out`` is not compared) and the policy file is not
    newer than it (a checkpoint retrained at the same path is run again)."""
    path = cfg.out / "report.json"
    if not path.exists():
        return None
    if Path(cfg.policy).is_file() and Path(cfg.policy).stat().st_mtime > path.stat().st_mtime:
        return None
    r = json.loads(path.read_text())
    ours = {k: str(v) for k, v in asdict(cfg).items() if k != "out"}
    same = {k: v for k, v in r.get("config", {}).items() if k != "out"} == ours
    sim_side = sim_side_shift(cfg)  # the same configuration with an older sim side (its latency) is run again
    same = same and r.get("sim_side", "absent") == json.loads(json.dumps(sim_side.as_dict() if sim_side else None))
    return (
        r
        if same and not r.get("interrupted") and r.get("error") is None and r.get("episodes") == cfg.episodes
        else None
    )


def _set_torch_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def main(args: Args) -> dict:
    args.policy = tuple(resolve_policy(p) for p in args.policy)  # short names (MANIFEST.json) become their files
    unknown = sorted(n for n in set(args.shifts) - set(SHIFTS) if JOIN not in n)
    if unknown:
        raise ValueError(f"--shifts {unknown}: the rows are {list(SHIFTS)}")
    combined = [n for n in args.shifts if n not in SHIFTS]
    for name in combined:
        spec_of(name)  # refused here, before any cell runs
    if args.workers < 1:
        raise ValueError(f"--workers {args.workers}: run at least one cell at a time")
    if args.camera == "none" and set(args.shifts) & set(MOUNTS):
        raise ValueError(f"--shifts {sorted(set(args.shifts) & set(MOUNTS))} correct camera frames: --camera twin")
    default = [n for n in SHIFTS if n not in MOUNT_ERRORS and (args.camera != "none" or n not in MOUNTS)]
    names = [n for n in SHIFTS if n in args.shifts] if args.shifts else default
    names += combined
    cells = [(p, name) for p in args.policy for name in names]
    if args.workers == 1:
        rows = [cell(p, name, args) for p, name in cells]
    else:
        threads = max(1, (os.cpu_count() or 1) // args.workers)
        # spawn: SAPIEN and torch are not fork-safe once the parent has imported them
        with ProcessPoolExecutor(
            args.workers, multiprocessing.get_context("spawn"), _set_torch_threads, (threads,)
        ) as pool:
            rows = list(pool.map(cell, *zip(*cells), [args] * len(cells)))
    scored = [r for r in rows if r["real_success"] is not None]
    pairs = [r["sim_success"] for r in scored], [r["real_success"] for r in scored]
    agree = agreement(*pairs) if len(scored) > 1 else None
    out = dict(
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
        command=" ".join(sys.argv),
        machine=platform.platform(),
        policy=list(args.policy),
        episodes=args.episodes,
        seed=args.seed,
        workers=args.workers,
        sim_shift=args.sim_shift,
        rows=rows,
        agreement=agree,
    )
    print(f"policies {', '.join(args.policy)} (camera {args.camera}), {args.episodes} episodes from seed {args.seed}")
    print("the sim side: " + ("in each row's condition" if args.sim_shift else "the nominal task in every row"))
    print(
        "| policy | shift | sim success | real success | real grasp | real drop | real collision | TCP dev (mm) "
        "| round trip p50 (ms) | refused | seeds won in sim only / on the twin only (McNemar p) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {_short(r['policy'])} | {r['shift']} | {100 * r['sim_success']:.0f} % | "
            f"{100 * r['real_success']:.0f} % | "
            f"{100 * r['real_grasp']:.0f} % | {100 * r['real_drop']:.0f} % | {100 * r['real_collision']:.0f} % | "
            f"{r['tcp_dev_mean_mm']:.1f} | {r['latency_p50_ms']:.0f} | {r['refused']} | "
            f"{r['paired']['sim_only']} / {r['paired']['real_only']} (p {r['paired']['mcnemar_p']:.2f}) |"
        )
    if agree is not None:
        pearson = "undefined (one side constant)" if agree["pearson"] is None else f"{agree['pearson']:.2f}"
        print(f"sim/twin agreement over {agree['pairs']} cells: MMRV {agree['mmrv']:.3f}, Pearson r {pearson}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


def _short(policy: str) -> str:
    """A checkpoint's run name (runs/NAME/checkpoints/latest.pt), an exported policy's file name, or 'expert'."""
    path = Path(policy)
    if path.suffix != ".pt":
        return policy
    return path.parent.parent.name if path.parent.name == "checkpoints" else path.stem


if __name__ == "__main__":
    main(tyro.cli(Args))
