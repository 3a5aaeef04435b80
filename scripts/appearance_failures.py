"""Which of an appearance shift's draws does a camera policy fail on? Joins the sim side's per-episode outcomes of
``sim2real-eval`` reports (``report.json``) with what the sim env drew for each of those episodes: every surface's
colour and procedural texture (pattern family, contrast), and where the task put its object.

A shift such as ``benchmarks/sim2real_gap.py``'s colours/textures draws a new appearance every episode, so a row's
success rate averages easy and hard scenes. Several policies evaluated on the same seeds under the same shift pool
their failures here, which tells a scene that defeats every policy (a property of the scene: the cube as yellow as
its tray) from one policy's bad luck.

    PYTHONPATH=. .venv/bin/python scripts/appearance_failures.py \\
        --reports runs/s2r_a/colours_textures/report.json runs/s2r_b/colours_textures/report.json \\
        --out runs/appearance_failures/colours_textures.json

Each factor is binned (by quartile, or by pattern family) and ranked by how far its bins' failure rates spread. Beside
it: its correlation with the number of policies that failed the episode, and that correlation's family-wise
permutation p-value (the outcomes shuffled over the episodes, against the best correlation of any factor), since the
most telling of twenty factors is partly picked for its luck. The draws are rebuilt by resetting the sim env as
``sim2real-eval`` built it (``load_policy`` with the report's sim-side randomisation) on the report's seeds: a reset
draws an episode's appearance from its seed alone.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

LUMA = np.array([0.299, 0.587, 0.114])
"""Rec. 601 luma weights: a colour's brightness as a grey camera frame would have it"""


@dataclass
class Args:
    reports: list[Path] = field(default_factory=list)
    """sim2real-eval report.json files of one env, shift and seed range (one per policy)"""
    out: Path = Path("runs/appearance_failures/appearance_failures.json")
    """the ranked factors, each with its bins' failure rates, and every episode's draws"""
    bins: int = 4
    """quantile bins per continuous factor"""
    permutations: int = 2000
    """shuffles of the outcomes over episodes for each correlation's family-wise p-value"""
    seed: int = 0
    """the shuffles' seed"""


def read_reports(paths: list[Path]) -> tuple[list[dict], list[int], np.ndarray]:
    """(the reports, their common seeds, failures: (reports, seeds) bool, the sim side's). One line if the reports
    do not share an env, a sim-side condition and seeds, or were not scored in the sim."""
    if not paths:
        raise ValueError("--reports: give at least one sim2real-eval report.json")
    reports = []
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"--reports {p}: no such file")
        try:
            r = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"--reports {p}: not JSON ({e})") from None
        if not isinstance(r, dict) or "env_id" not in r.get("config", {}) or not r.get("per_episode"):
            raise ValueError(f"--reports {p}: not a sim2real-eval report.json (no config.env_id or per_episode)")
        if not r.get("sim_side"):
            raise ValueError(f"--reports {p}: its sim side ran with no shift, so there are no draws to join")
        reports.append(r)
    first = reports[0]
    from maniskill_irb120.envs.randomization import APPEARANCE_FIELDS, Randomization

    condition = Randomization.from_any(first["sim_side"])  # a field added since a report was written reads as off
    if not set(APPEARANCE_FIELDS) & set(condition.active()):
        raise ValueError(f"--reports {paths[0]}: its sim side drew no appearance ({', '.join(APPEARANCE_FIELDS)} off)")
    seeds = [e["seed"] for e in first["per_episode"]]
    for p, r in zip(paths, reports):
        if r["config"]["env_id"] != first["config"]["env_id"]:
            raise ValueError(f"--reports {p}: another env_id than {paths[0]}'s; join reports of one condition")
        if Randomization.from_any(r["sim_side"]) != condition:
            raise ValueError(f"--reports {p}: another sim_side than {paths[0]}'s; join reports of one condition")
        if [e["seed"] for e in r["per_episode"]] != seeds:
            raise ValueError(f"--reports {p}: other episode seeds than {paths[0]}'s")
        if any(e["sim_success"] is None for e in r["per_episode"]):
            raise ValueError(f"--reports {p}: an episode without a sim outcome")
    failed = np.array([[not e["sim_success"] for e in r["per_episode"]] for r in reports])
    return reports, seeds, failed


def episode_draws(report: dict, seeds: list[int]) -> list[dict]:
    """Each seed's appearance draws and object pose, from the sim env ``sim2real-eval`` built for ``report``."""
    from maniskill_irb120.envs.randomization import Randomization
    from maniskill_irb120.sim2real.policy import load_policy

    cfg = report["config"]
    env, _ = load_policy(
        cfg["policy"], cfg["env_id"], cfg["command_mode"], cfg["actions"], Randomization.from_any(report["sim_side"])
    )
    out = []
    try:
        for seed in seeds:
            env.reset(seed=seed)
            u = env.unwrapped
            d = {k: np.round(v[0].numpy().astype(float), 4).tolist() for k, v in u.randomization_draws.items()}
            d["object_xy"] = np.round(u.target_object.pose.p[0, :2].numpy().astype(float), 4).tolist()  # 0.1 mm
            out.append(d)
    finally:
        env.close()
    return out


def factors(draws: list[dict]) -> dict[str, tuple[np.ndarray, bool]]:
    """Factor name -> (value per episode, categorical). Per surface: its colour's distance to the object's and its
    brightness; its pattern family and contrast where textured; the object's colour and place."""
    from maniskill_irb120.envs.appearance import PATTERNS

    surfaces = sorted(k[len("rgb_") :] for k in draws[0] if k.startswith("rgb_"))
    obj = np.array([d["rgb_object"] for d in draws])
    out: dict[str, tuple[np.ndarray, bool]] = {}
    for s in surfaces:
        rgb = np.array([d["rgb_" + s] for d in draws])
        if s != "object":
            out[f"{s}: colour distance to the object"] = (np.linalg.norm(rgb - obj, axis=1), False)
        out[f"{s}: brightness"] = (rgb @ LUMA, False)
        pattern = np.array([d["pattern_" + s] for d in draws]).astype(int)
        if (pattern >= 0).any():
            names = np.array(["none", *PATTERNS])
            out[f"{s}: pattern"] = (names[pattern + 1], True)
            out[f"{s}: texture contrast"] = (np.array([d["contrast_" + s] for d in draws]), False)
    for c, name in enumerate(("red", "green", "blue")):
        out[f"object: {name}"] = (obj[:, c], False)
    xy = np.array([d["object_xy"] for d in draws])
    out["object: x (m)"], out["object: y (m)"] = (xy[:, 0], False), (xy[:, 1], False)
    return out


def familywise_p(values: np.ndarray, count: np.ndarray, permutations: int, seed: int) -> np.ndarray:
    """(factors,) p-values of each factor's |correlation| with ``count`` against the largest |correlation| of any
    factor when ``count`` is shuffled over the episodes: a factor picked out of many as the most telling one is not
    credited with the luck of the pick. ``values``: (factors, episodes), each with some spread."""
    z = (values - values.mean(axis=1, keepdims=True)) / values.std(axis=1, keepdims=True)

    def corr(c: np.ndarray) -> np.ndarray:
        return np.abs(z @ ((c - c.mean()) / c.std())) / len(c)

    seen = corr(count)
    rng = np.random.default_rng(seed)
    top = np.array([corr(rng.permutation(count)).max() for _ in range(permutations)])
    return (1 + (top[None, :] >= seen[:, None] - 1e-12).sum(axis=1)) / (1 + permutations)


def rank(
    named: dict[str, tuple[np.ndarray, bool]], failed: np.ndarray, bins: int, permutations: int = 0, seed: int = 0
) -> list[dict]:
    """Per factor: its bins (range or category, episodes, failure rate over every report's episodes in it), the
    spread of those rates, the correlation with the count of reports that failed and, with ``permutations``, that
    correlation's family-wise p-value (:func:`familywise_p`); the widest spread first."""
    count = failed.sum(axis=0).astype(float)
    tested = [k for k, (v, cat) in named.items() if not cat and np.std(v) > 0]
    p = {}
    if permutations and tested and np.std(count) > 0:
        p = dict(zip(tested, familywise_p(np.array([named[k][0] for k in tested]), count, permutations, seed)))
    rows = []
    for name, (v, categorical) in named.items():
        if categorical:
            groups = [(str(c), v == c) for c in sorted(set(v.tolist()))]
        else:
            edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
            idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
            groups = [(f"{edges[i]:.3g}-{edges[i + 1]:.3g}", idx == i) for i in range(len(edges) - 1)]
        table = [dict(bin=b, episodes=int(m.sum()), failure=float(failed[:, m].mean())) for b, m in groups if m.any()]
        rates = [t["failure"] for t in table]
        corr = None
        if not categorical and np.std(v) > 0 and np.std(count) > 0:
            corr = float(np.corrcoef(v, count)[0, 1])
        p_value = float(p[name]) if name in p else None
        rows.append(dict(factor=name, spread=max(rates) - min(rates), correlation=corr, p=p_value, bins=table))
    return sorted(rows, key=lambda r: -r["spread"])


def check(a: Args) -> None:
    """Refuse what cannot be joined before an env is built."""
    if a.bins < 2:
        raise ValueError(f"--bins {a.bins}: at least 2")
    if a.permutations < 0:
        raise ValueError(f"--permutations {a.permutations}: 0 (none) or more")
    read_reports(a.reports)


def main(a: Args) -> dict:
    reports, seeds, failed = read_reports(a.reports)
    draws = episode_draws(reports[0], seeds)
    ranked = rank(factors(draws), failed, a.bins, a.permutations, a.seed)
    result = dict(
        reports=[str(p) for p in a.reports],
        policies=[r["config"]["policy"] for r in reports],
        env_id=reports[0]["config"]["env_id"],
        sim_side=reports[0]["sim_side"],
        seeds=[seeds[0], seeds[-1]],
        failure=float(failed.mean()),
        per_policy_failure=[float(f.mean()) for f in failed],
        factors=ranked,
        episodes=[dict(seed=s, failed=int(failed[:, i].sum()), draws=draws[i]) for i, s in enumerate(seeds)],
    )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result) + "\n")  # one line: 100 episodes of draws are most of it
    print(
        f"{len(reports)} report(s), {len(seeds)} episodes each (seeds {seeds[0]}..{seeds[-1]}), "
        f"{result['env_id']}: failure {result['failure']:.2f} over all of them"
    )
    print("| factor | spread | correlation (family-wise p) | failure rate per bin (episodes) |")
    print("|---|---|---|---|")
    for r in ranked:
        corr = "–" if r["correlation"] is None else f"{r['correlation']:+.2f}"
        corr += "" if r["p"] is None else f" ({r['p']:.3f})"
        cells = "; ".join(f"{b['bin']}: {b['failure']:.2f} ({b['episodes']})" for b in r["bins"])
        print(f"| {r['factor']} | {r['spread']:.2f} | {corr} | {cells} |")
    print(f"wrote {a.out}")
    return result


def cli(argv: Optional[list[str]] = None) -> object:
    """The command line (``argv``, default ``sys.argv[1:]``): bad input is one line and exit status 2."""
    from benchmarks.lib.cli import entry

    return entry("scripts.appearance_failures", Args, main, check, argv=argv)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    cli()
