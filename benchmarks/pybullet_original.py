"""Times the original report's PyBullet action loop (``benchmarks.lib.pybullet_loop``, which says how it was
rebuilt) in the three modes of the original report's Table 5.1, for speed comparisons with the ManiSkill env.

    python -m benchmarks.pybullet_original --quick
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from benchmarks.lib.cli import entry
from benchmarks.lib.pybullet_loop import MODES, markdown_table, measure, p


@dataclass
class Args:
    """Time the original report's PyBullet action loop in the three modes of the original report's Table 5.1."""

    n_actions: int = 200
    """actions per mode"""
    realtime_n_actions: int | None = None
    """cap for the (wall-clock paced, slow by design) render_realtime mode; default n_actions"""
    seed: int = 0
    modes: tuple[str, ...] = tuple(MODES)
    json: Path | None = None
    """also write all results (per-action times included) to this JSON file"""
    quick: bool = False
    """a few actions per mode (< 30 s in all), for smoke tests"""


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before PyBullet starts (``benchmarks.lib.cli`` makes it one
    line and exit status 2): an unknown --modes, --n-actions or --realtime-n-actions below 1."""
    unknown = [m for m in args.modes if m not in MODES]
    if unknown:
        raise ValueError(f"--modes {unknown}: the modes are {list(MODES)}")
    if args.n_actions < 1:
        raise ValueError(f"--n-actions {args.n_actions}: expected 1 or more")
    if args.realtime_n_actions is not None and args.realtime_n_actions < 1:
        raise ValueError(f"--realtime-n-actions {args.realtime_n_actions}: expected 1 or more (or leave it out)")


def main(args: Args) -> list[dict]:
    check(args)
    n, n_rt = args.n_actions, args.realtime_n_actions
    if args.quick:
        n, n_rt = 10, 5
    results = []
    for mode in args.modes:
        k = n if (mode != "render_realtime" or n_rt is None) else min(n, n_rt)
        results.append(measure(mode, k, args.seed))
    print("\n" + markdown_table(results))  # (a newline: PyBullet's URDF warnings do not end with one)
    for r in results:
        print(
            f"{r['mode']}: converged {r['n_converged']}/{r['n']}, timeouts {r['n_timeouts']}, "
            f"skipped (IK) {r['n_skipped']}, collisions/resets {r['n_collisions']}, "
            f"sim time/action {r['sim_time_per_action']:.3f} s"
        )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"pybullet": p.getAPIVersion(), "results": results}, indent=1))
    return results


if __name__ == "__main__":
    entry("benchmarks.pybullet_original", Args, main, check)
