"""How often a policy switches its gripper: per episode, the valve switches it commands (the commanded state
changing, ``agent.gripper_commanded_closed``) before the first grasp and in all, per second at the task's control
rate, and the episode's success. A real MetalWork gripper is pneumatic: each switch is a valve stroke, so a policy
that alternates its gripper command on the approach strokes the valve at up to the control rate
(docs/notes/gripper-chatter.md).

    .venv/bin/python scripts/gripper_chatter.py --policy expert ppo-state-tableclearing-sel-s1 \\
        --episodes 6 --seed 5000 --json runs/gripper_chatter.json

Each policy plays in the sim env ``sim2real-eval`` builds for it (``load_policy``, no shift), deterministically:
the same seeds give the same counts.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np


@dataclass
class Args:
    policy: list[str] = field(default_factory=lambda: ["expert"])
    """'expert', checkpoint files or names of a policies MANIFEST.json, each played in turn"""
    env_id: str = "TableClearing-IRB120-v1"
    """the task"""
    episodes: int = 6
    """deterministic episodes per policy, one a seed"""
    seed: int = 5000
    """the first episode's seed (5000: the shift table's first)"""
    max_steps: int = 200
    """steps per episode at most"""
    json: Optional[Path] = None
    """write the rows here"""


def check(a: Args) -> None:
    """Refuse what cannot run before an env is built: counts, the env id, each policy's file and its task."""
    if a.episodes < 1 or a.max_steps < 1:
        raise ValueError(f"--episodes {a.episodes}, --max-steps {a.max_steps}: each must be at least 1")
    if a.seed < 0:
        raise ValueError(f"--seed {a.seed}: episode seeds are 0 or more")
    from maniskill_irb120.envs import check_env_id
    from maniskill_irb120.sim2real.policy import read_policy_section, resolve_policy

    check_env_id(a.env_id)
    for name in a.policy:
        path = resolve_policy(name)
        if name != "expert":
            trained_on = read_policy_section(Path(path), f"--policy {path}")["env_id"]
            if trained_on != a.env_id:
                raise ValueError(f"--policy {name}: trained on {trained_on}, not --env-id {a.env_id}")


def switches(closed: np.ndarray) -> int:
    """Valve switches in a sequence of commanded gripper states (True: closed)."""
    closed = np.asarray(closed, dtype=bool)
    return int((closed[1:] != closed[:-1]).sum())


def finger_slots(u, obs) -> list[int] | None:
    """Where the fingers sit in a flat state observation ``obs`` of the env ``u``: the two finger joints' qpos and
    qvel and ``gripper_opening``, found in the state dict ManiSkill flattens into it (None: ``obs`` is not that
    flattening, e.g. a camera policy's or one with keys dropped)."""
    import torch
    from mani_skill.utils import common

    if not isinstance(obs, torch.Tensor) or obs.ndim != 2:
        return None
    state = u._get_obs_state_dict(u.get_info())
    if not torch.equal(common.flatten_state_dict(state, use_torch=True).to(obs.device), obs.to(torch.float32)):
        return None
    slots, at = [], 0
    for group, values in state.items():
        for key, v in values.items() if isinstance(values, dict) else [("", values)]:
            width = v.reshape(v.shape[0], -1).shape[1]
            if group == "agent" and key in ("qpos", "qvel"):
                slots += [at + width - 2, at + width - 1]  # the two finger joints end the robot's joints
            elif group == "agent" and key == "gripper_opening":
                slots.append(at)
            at += width
    return slots if len(slots) == 5 else None


def play(policy: str, env_id: str, seeds: list[int], max_steps: int) -> dict:
    """``policy``'s episodes at ``seeds``: per episode the commanded gripper states, the finger opening and the
    events, and their totals. For a state policy, each step before the grasp is also acted on with only its finger
    observation swapped for the next step's: how often that alone flips the gripper command says whether the
    command follows the fingers' own state."""
    import torch

    from maniskill_irb120.sim2real.policy import load_policy

    env, make = load_policy(policy, env_id, "tool_delta", "as-trained", None, expert_obs_mode="state")
    try:
        pol = make(env)
        u = env.unwrapped
        episodes, slots = [], None
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            pol.reset(seed)
            if seed == seeds[0] and policy != "expert":  # the layout is the policy's, the same every episode
                slots = finger_slots(u, obs)
            closed = [bool(u.agent.gripper_commanded_closed[0])]
            opening = [float(u.agent.gripper_opening[0])]
            seen, grip = [obs], []
            grasped_at, info = None, {}
            for t in range(max_steps):
                action = pol.act(obs)
                grip.append(float(torch.as_tensor(action).reshape(-1)[4]))
                obs, _, term, trunc, info = env.step(action)
                seen.append(obs)
                closed.append(bool(u.agent.gripper_commanded_closed[0]))
                opening.append(float(u.agent.gripper_opening[0]))
                if grasped_at is None and bool(info.get("grasped", torch.zeros(1, dtype=torch.bool))[0]):
                    grasped_at = t + 1
                if bool(term[0]) or bool(trunc[0]):
                    break
            steps = len(closed) - 1
            reach = grasped_at if grasped_at is not None else steps
            approach = opening[1:reach] or opening[:1]  # the steps before the grasp (the start, for a 1-step one)
            flipped = None
            if slots is not None:  # the command with the fingers as the next step observed them, all else kept
                flipped = 0
                for t in range(reach - 1):
                    swapped = seen[t].clone()
                    swapped[:, slots] = seen[t + 1][:, slots]
                    flipped += int(np.sign(float(torch.as_tensor(pol.act(swapped)).reshape(-1)[4])) != np.sign(grip[t]))
            episodes.append(
                dict(
                    seed=seed,
                    steps=steps,
                    grasped_at=grasped_at,
                    switches_before_grasp=switches(closed[: reach + 1]),
                    switches=switches(closed),
                    opening_start_mm=opening[0] * 1e3,
                    opening_before_grasp_mm=[min(approach) * 1e3, max(approach) * 1e3],
                    swap_flips=flipped,
                    swap_steps=reach - 1 if slots is not None else None,
                    success=bool(info["success"][0]),
                )
            )
        rate = float(u.control_freq)
    finally:
        env.close()
    total_steps = sum(e["steps"] for e in episodes)
    probed = [e for e in episodes if e["swap_flips"] is not None and e["swap_steps"] > 0]
    return dict(
        policy=policy,
        env_id=env_id,
        control_hz=rate,
        episodes=episodes,
        switches_per_episode=float(np.mean([e["switches"] for e in episodes])),
        switches_before_grasp_per_episode=float(np.mean([e["switches_before_grasp"] for e in episodes])),
        switches_per_s=sum(e["switches"] for e in episodes) / total_steps * rate,
        opening_start_mm=float(np.mean([e["opening_start_mm"] for e in episodes])),
        opening_before_grasp_mm=[
            float(min(e["opening_before_grasp_mm"][0] for e in episodes)),
            float(max(e["opening_before_grasp_mm"][1] for e in episodes)),
        ],
        swap_flip_share=(
            sum(e["swap_flips"] for e in probed) / sum(e["swap_steps"] for e in probed) if probed else None
        ),
        success=float(np.mean([e["success"] for e in episodes])),
    )


def main(a: Args) -> list[dict]:
    seeds = list(range(a.seed, a.seed + a.episodes))
    rows = []
    print(
        "| policy | episodes | valve switches per episode (before the grasp) | switches per s "
        "| finger opening before the grasp, mm (at the start) | command flipped by the next step's fingers | success |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in a.policy:
        r = play(name, a.env_id, seeds, a.max_steps)
        rows.append(r)
        lo, hi = r["opening_before_grasp_mm"]
        swap = "–" if r["swap_flip_share"] is None else f"{r['swap_flip_share']:.0%}"
        print(
            f"| {name} | {len(seeds)} | {r['switches_per_episode']:.1f} ({r['switches_before_grasp_per_episode']:.1f})"
            f" | {r['switches_per_s']:.1f} | {lo:.0f}–{hi:.0f} ({r['opening_start_mm']:.0f}) | {swap}"
            f" | {r['success']:.2f} |",
            flush=True,
        )
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(dict(command=" ".join(sys.argv), rows=rows), indent=2) + "\n")
    return rows


def cli(argv: Optional[list[str]] = None) -> object:
    """The command line (``argv``, default ``sys.argv[1:]``): bad input is one line and exit status 2."""
    from benchmarks.lib.cli import entry

    return entry("scripts.gripper_chatter", Args, main, check, argv=argv)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    cli()
