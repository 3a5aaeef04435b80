"""Does a camera student fail under a shift because it no longer finds the cube, or because it acts wrongly on a
cube it still finds? Plays a DAgger student (a training checkpoint that holds its auxiliary head) in the sim under
``--shift`` and with no shift, on the same episode seeds, and records at every step:

- its **perception**: the auxiliary head's reading of the cube's place relative to the TCP (what the student's
  encoder was trained to hold, ``agents.dagger --aux-weight``), against the truth (``privileged_aux``);
- its **action** against the state teacher's label for the same state (what DAgger would have taught it there);
- the TCP's height and the episode's end (success, collided).

It prints, per condition and per TCP height band, the median error of both, and writes the per-step arrays to
``--out``. A student whose perception error grows under the shift while its action error follows is fooled by the
image; one whose perception holds while its actions part from the teacher's reads the cube but acts on other
features.

    PYTHONPATH=. .venv/bin/python scripts/perception_probe.py \\
        --checkpoint runs/ts_drmix_2x/ts_drmix_tableclearing_s1_2x/checkpoints/latest.pt \\
        --shift "color=0.25,texture=1,roughness=0.3,specular=0.8" --episodes 30 --seed 5000 \\
        --out runs/perception_probe/drmix_2x_textures.json

The sim env is ``sim2real-eval``'s own (``load_policy`` with the shift as its ``sim_shift``), so the episodes are
those of ``benchmarks/sim2real_gap.py``'s rows for the same seeds. Deterministic for a given seed.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

BANDS = ((0.15, 1.0), (0.06, 0.15), (0.0, 0.06))
"""TCP heights (m): the approach from afar, the descent, the last 6 cm where the stop must come"""


@dataclass
class Args:
    checkpoint: Path
    """an agents.dagger training checkpoint that keeps its auxiliary head (a run's latest.pt; best.pt drops it)"""
    shift: str
    """the shifted condition, in Randomization.parse syntax"""
    episodes: int = 30
    """deterministic episodes per condition, one a seed"""
    seed: int = 5000
    """the first episode's seed, in both conditions (5000: the shift table's first)"""
    teacher: Optional[Path] = None
    """the state teacher whose labels the actions are held to (default: the checkpoint's --teacher)"""
    out: Path = Path("runs/perception_probe/probe.json")
    """the summary; the per-step arrays go beside it (.npz)"""


def check(a: Args) -> None:
    """Refuse what cannot run before an env is built: counts, seeds, the shift's syntax, a checkpoint without what
    the probe reads."""
    if a.episodes < 1:
        raise ValueError(f"--episodes {a.episodes}: at least 1")
    if a.seed < 0:
        raise ValueError(f"--seed {a.seed}: episode seeds are 0 or more")
    if not a.checkpoint.is_file():
        raise FileNotFoundError(f"--checkpoint {a.checkpoint}: no such file")
    from maniskill_irb120.envs.randomization import Randomization

    try:
        Randomization.parse(a.shift)
    except (ValueError, TypeError) as e:
        raise ValueError(f"--shift {a.shift!r}: {e}") from None
    load(a.checkpoint, a.teacher)  # its head, frame and teacher, named before an env starts


def load(checkpoint: Path, teacher: Path | None):
    """(actor, aux head, teacher path, env id) from a DAgger training checkpoint; one line if it lacks one."""
    import torch

    from agents.dagger import aux_head_for, load_policy

    actor, ckpt = load_policy(checkpoint, torch.device("cpu"))
    if ckpt.get("aux_head") is None:
        raise ValueError(f"--checkpoint {checkpoint} has no auxiliary head (a best.pt drops it: use latest.pt)")
    args = ckpt["args"]
    if args.get("action_frame") != "tool":
        raise ValueError(f"--checkpoint {checkpoint} acts in the {args.get('action_frame')} frame; tool only")
    head = aux_head_for(actor, torch.device("cpu"), bool(args.get("aux_mount")))
    head.load_state_dict(ckpt["aux_head"])
    head.eval()
    teacher = teacher or (Path(args["teacher"]) if args.get("teacher") else None)
    if teacher is None:
        raise ValueError(f"--checkpoint {checkpoint} was not taught by a state teacher; give --teacher")
    return actor, head, teacher, args["env_id"]


def play(checkpoint: Path, env_id: str, actor, head, teacher: Path, seeds: list[int], shift: str | None) -> dict:
    """Every step of the student's episodes at ``seeds`` under ``shift`` (None: nominal). The student acts through
    ``sim2real-eval``'s own policy wrapper; ``head_act`` is the same action recomputed from the features the
    auxiliary head reads, so a test can hold the two to each other."""
    import torch

    from agents.common.envs import TeacherLabels
    from maniskill_irb120.envs.randomization import Randomization
    from maniskill_irb120.sim2real.policy import load_policy

    env, make = load_policy(
        str(checkpoint), env_id, "tool_delta", "as-trained", Randomization.parse(shift) if shift else None
    )
    env = TeacherLabels(env, teacher, frame="tool", aux=True)
    pol = make(env)
    keys = ("episode", "z", "aux_err_mm", "aux_pred", "aux_true", "act", "head_act", "label")
    rows: dict[str, list] = {k: [] for k in keys}
    ends = []
    try:
        for i, seed in enumerate(seeds):
            obs, info = env.reset(seed=seed)
            pol.reset(seed)
            while True:
                with torch.no_grad():
                    feats = actor.features(obs)
                    pred = head(feats)[0, :3]
                    rows["head_act"].append(torch.tanh(actor.head(feats))[0].numpy())
                a = pol.act(obs)
                true = info["expert_aux"][0, :3].float()
                rows["episode"].append(i)
                rows["z"].append(float(env.unwrapped.agent.tcp_pose.p[0, 2]))
                rows["aux_err_mm"].append((pred - true).numpy() * 100.0)  # decimetres -> mm
                rows["aux_pred"].append(pred.numpy() * 100.0)
                rows["aux_true"].append(true.numpy() * 100.0)
                rows["act"].append(a.numpy())
                rows["label"].append(info["expert_action"][0].float().numpy())
                obs, _, term, trunc, info = env.step(a)
                if bool(term[0]) or bool(trunc[0]):
                    break
            ends.append(
                dict(seed=seed, success=bool(info["success"][0]), collided=bool(info.get("collided", [False])[0]))
            )
            print(f"  {'shifted' if shift else 'nominal'} seed {seed}: {ends[-1]}", flush=True)
    finally:
        env.close()
    out = {k: np.array(v) for k, v in rows.items()}
    out["ends"] = ends
    return out


def summary(run: dict) -> dict:
    """Median |aux error| in x/y/z (mm) and median |action - label| (translation, tool frame) per height band, over
    every step and over the collided episodes' steps alone."""
    collided = {i for i, e in enumerate(run["ends"]) if e["collided"]}
    res = {}
    for lo, hi in BANDS:
        band = (run["z"] >= lo) & (run["z"] < hi)
        for which, mask in (("all", band), ("collided", band & np.isin(run["episode"], list(collided)))):
            if not mask.any():
                continue
            err = np.abs(run["aux_err_mm"][mask])
            act = np.linalg.norm(run["act"][mask, :3] - run["label"][mask, :3], axis=1)
            res[f"{which} z {lo * 1e3:.0f}-{min(hi, 0.3) * 1e3:.0f} mm"] = dict(
                steps=int(mask.sum()),
                aux_err_x=float(np.median(err[:, 0])),
                aux_err_y=float(np.median(err[:, 1])),
                aux_err_z=float(np.median(err[:, 2])),
                aux_err_xy_p90=float(np.percentile(np.linalg.norm(run["aux_err_mm"][mask, :2], axis=1), 90)),
                action_err=float(np.median(act)),
            )
    return res


def main(a: Args) -> dict:
    actor, head, teacher, env_id = load(a.checkpoint, a.teacher)
    seeds = list(range(a.seed, a.seed + a.episodes))
    result = {"checkpoint": str(a.checkpoint), "shift": a.shift, "seeds": [seeds[0], seeds[-1]], "conditions": {}}
    runs = {}
    for name, shift in (("none", None), ("shifted", a.shift)):
        runs[name] = run = play(a.checkpoint, env_id, actor, head, teacher, seeds, shift)
        ends = run["ends"]
        for i, e in enumerate(ends):  # the cube as read over the descent, the part of the episode that decides
            m = (run["episode"] == i) & (run["z"] < 0.15) & (run["z"] >= 0.03)
            xy = np.linalg.norm(run["aux_err_mm"][m, :2], axis=1)
            e["descent_aux_err_xy_mm"] = float(np.median(xy)) if m.any() else None
        result["conditions"][name] = dict(
            success=sum(e["success"] for e in ends),
            collided=sum(e["collided"] for e in ends),
            episodes=len(ends),
            bands=summary(run),
            ends=ends,
        )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1) + "\n")
    np.savez_compressed(
        a.out.with_suffix(".npz"),
        **{f"{n}_{k}": v for n, r in runs.items() for k, v in r.items() if k != "ends"},
    )
    print("| condition | band | steps | aux err x / y / z (mm, median) | aux err xy p90 | action err (median) |")
    print("|---|---|---|---|---|---|")
    for name, c in result["conditions"].items():
        for band, s in c["bands"].items():
            print(
                f"| {name} ({c['success']}/{c['episodes']}, {c['collided']} collided) | {band} | {s['steps']} | "
                f"{s['aux_err_x']:.1f} / {s['aux_err_y']:.1f} / {s['aux_err_z']:.1f} | {s['aux_err_xy_p90']:.1f} | "
                f"{s['action_err']:.3f} |"
            )
    for name, c in result["conditions"].items():
        for end in ("success", "collided"):
            errs = [e["descent_aux_err_xy_mm"] for e in c["ends"] if e[end] and e["descent_aux_err_xy_mm"] is not None]
            if errs:
                print(
                    f"{name}, {end} episodes ({len(errs)}): the cube read {np.median(errs):.1f} mm off in x/y over the "
                    f"descent (median of the episodes' medians; max {max(errs):.1f})"
                )
    print(f"wrote {a.out}")
    return result


def cli(argv: Optional[list[str]] = None) -> object:
    """The command line (``argv``, default ``sys.argv[1:]``): bad input is one line and exit status 2."""
    from benchmarks.lib.cli import entry

    return entry("scripts.perception_probe", Args, main, check, argv=argv)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    cli()
