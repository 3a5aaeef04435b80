"""How often a policy switches its gripper: per episode, the valve switches it commands (the commanded state
changing, ``agent.gripper_commanded_closed``) before the first grasp and in all, per second at the task's control
rate, and the episode's success. A real MetalWork gripper is pneumatic: each switch is a valve stroke, and fingers
told to reverse every step never finish a stroke, so a policy that alternates its gripper command on the approach
wears the valve and shows the camera fingers the sim never drew half-way.

    PYTHONPATH=. .venv/bin/python scripts/gripper_chatter.py --policy expert ppo-state-tableclearing-s1 \\
        --episodes 6 --seed 5000 --json runs/gripper_chatter.json

Each policy plays in the sim env ``sim2real-eval`` builds for it (``load_policy``, no shift), deterministically:
the same seeds give the same counts.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ENV_ID = "TableClearing-IRB120-v1"


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    class Parser(argparse.ArgumentParser):
        def error(self, message):  # one line, exit 2
            print(f"gripper_chatter.py: {message}", file=sys.stderr)
            raise SystemExit(2)

    p = Parser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", nargs="+", default=["expert"], help="'expert', files or MANIFEST names")
    p.add_argument("--env-id", default=ENV_ID)
    p.add_argument("--episodes", type=int, default=6, help="episodes per policy")
    p.add_argument("--seed", type=int, default=5000, help="first episode seed")
    p.add_argument("--max-steps", type=int, default=200, help="steps per episode at most")
    p.add_argument("--json", type=Path, default=None, help="write the rows here")
    a = p.parse_args(argv)
    if a.episodes < 1 or a.max_steps < 1:
        p.error("--episodes and --max-steps must be at least 1")
    if a.seed < 0:
        p.error(f"--seed {a.seed}: episode seeds are 0 or more")
    from maniskill_irb120.envs import check_env_id
    from maniskill_irb120.errors import UsageError
    from maniskill_irb120.sim2real.policy import resolve_policy

    try:
        check_env_id(a.env_id)
        for name in a.policy:
            resolve_policy(name)
    except UsageError as e:
        p.error(str(e))
    return a


def switches(closed: np.ndarray) -> int:
    """Valve switches in a sequence of commanded gripper states (True: closed)."""
    closed = np.asarray(closed, dtype=bool)
    return int((closed[1:] != closed[:-1]).sum())


def play(policy: str, env_id: str, seeds: list[int], max_steps: int) -> dict:
    """``policy``'s episodes at ``seeds``: per episode the commanded gripper states and events, and their totals."""
    import torch

    from maniskill_irb120.sim2real.policy import load_policy

    env, make = load_policy(policy, env_id, "tool_delta", "as-trained", None, expert_obs_mode="state")
    try:
        pol = make(env)
        u = env.unwrapped
        episodes = []
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            pol.reset(seed)
            closed = [bool(u.agent.gripper_commanded_closed[0])]
            grasped_at, info = None, {}
            for t in range(max_steps):
                obs, _, term, trunc, info = env.step(pol.act(obs))
                closed.append(bool(u.agent.gripper_commanded_closed[0]))
                if grasped_at is None and bool(info.get("grasped", torch.zeros(1, dtype=torch.bool))[0]):
                    grasped_at = t + 1
                if bool(term[0]) or bool(trunc[0]):
                    break
            steps = len(closed) - 1
            before = closed[: (grasped_at if grasped_at is not None else steps) + 1]
            episodes.append(
                dict(
                    seed=seed,
                    steps=steps,
                    grasped_at=grasped_at,
                    switches_before_grasp=switches(before),
                    switches=switches(closed),
                    success=bool(info["success"][0]),
                )
            )
        rate = float(u.control_freq)
    finally:
        env.close()
    total_steps = sum(e["steps"] for e in episodes)
    return dict(
        policy=policy,
        env_id=env_id,
        control_hz=rate,
        episodes=episodes,
        switches_per_episode=float(np.mean([e["switches"] for e in episodes])),
        switches_before_grasp_per_episode=float(np.mean([e["switches_before_grasp"] for e in episodes])),
        switches_per_s=sum(e["switches"] for e in episodes) / total_steps * rate,
        success=float(np.mean([e["success"] for e in episodes])),
    )


def main(argv: list[str] | None = None) -> list[dict]:
    from maniskill_irb120.errors import UsageError

    a = parse(argv)
    seeds = list(range(a.seed, a.seed + a.episodes))
    rows = []
    for name in a.policy:
        try:
            r = play(name, a.env_id, seeds, a.max_steps)
        except UsageError as e:  # e.g. a policy of another task or control mode, refused by load_policy
            print(f"gripper_chatter.py: {e}", file=sys.stderr)
            raise SystemExit(2) from None
        if not rows:  # the header once the first policy has played (a refused one prints only its line)
            print("| policy | episodes | valve switches per episode (before the grasp) | switches per s | success |")
            print("|---|---|---|---|---|")
        rows.append(r)
        print(
            f"| {name} | {len(seeds)} | {r['switches_per_episode']:.1f} ({r['switches_before_grasp_per_episode']:.1f})"
            f" | {r['switches_per_s']:.1f} | {r['success']:.2f} |",
            flush=True,
        )
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(dict(command=" ".join(sys.argv), rows=rows), indent=2) + "\n")
    return rows


if __name__ == "__main__":
    main()
