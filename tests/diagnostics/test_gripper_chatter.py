"""``scripts/gripper_chatter.py``: it counts the valve switches a policy commands, in the sim, from the agent's
commanded gripper state. The scripted expert closes once, at its grasp; the committed GraspLift PPO teacher switches
more often before its grasp, and the JSON carries the counts per episode."""

from __future__ import annotations

import json

import pytest


def test_switches_counts_changes_of_the_commanded_state(repo_script):
    chatter = repo_script("gripper_chatter")
    assert chatter.switches([False, False, True, True]) == 1
    assert chatter.switches([False, True, False, True, False]) == 4
    assert chatter.switches([True]) == 0


def test_the_expert_switches_once_before_its_grasp_and_the_ppo_teacher_more(tmp_path, capsys, repo_script):
    chatter = repo_script("gripper_chatter")
    out = tmp_path / "chatter.json"
    rows = chatter.cli(
        [
            "--env-id",
            "GraspLift-IRB120-v1",
            "--policy",
            "expert",
            "ppo-state-grasplift-sel-s1",
            "--episodes",
            "1",
            "--seed",
            "5000",
            "--json",
            str(out),
        ]  # fmt: skip
    )
    expert, ppo = rows
    (ep,) = expert["episodes"]
    assert ep["success"] and ep["grasped_at"] is not None and ep["switches_before_grasp"] == 1
    assert expert["control_hz"] == 20.0
    assert expert["switches_per_s"] == ep["switches"] / ep["steps"] * 20.0
    assert ppo["episodes"][0]["switches_before_grasp"] > 1
    assert expert["opening_start_mm"] == ppo["opening_start_mm"] == pytest.approx(26.0, abs=0.5)  # fingers open
    # the probe swaps a state policy's finger observation; the expert reads the simulator, not an observation
    assert expert["swap_flip_share"] is None and 0 <= ppo["swap_flip_share"] <= 1
    assert ppo["episodes"][0]["swap_steps"] == ppo["episodes"][0]["grasped_at"] - 1
    assert json.loads(out.read_text())["rows"][1]["policy"] == "ppo-state-grasplift-sel-s1"
    table = capsys.readouterr().out
    assert "| expert | 1 | 1.0 (1.0) |" in table
