"""scripts/appearance_failures.py: the per-episode draws it joins are those the sim side drew for each seed, its
ranking finds the factor the failures follow, and it refuses reports that cannot be joined."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

from maniskill_irb120.envs.randomization import Randomization

SHIFT = "color=0.25,texture=1"
SEEDS = [7, 8, 9, 10, 11, 12]


@pytest.fixture
def tool(repo_script):
    return repo_script("appearance_failures")


def report(tmp_path, name, failed_seeds, seeds=SEEDS, shift=SHIFT, env_id="GraspLift-IRB120-v1"):
    """A sim2real-eval report.json as the tool reads it: the scripted expert's sim side under ``shift``."""
    path = tmp_path / name / "report.json"
    path.parent.mkdir(parents=True)
    config = dict(policy="expert", env_id=env_id, command_mode="tool_delta", actions="as-trained")
    per_episode = [dict(seed=s, sim_success=s not in failed_seeds, real_success=None) for s in seeds]
    sim_side = Randomization.parse(shift).as_dict() if shift else None
    path.write_text(json.dumps(dict(config=config, sim_side=sim_side, per_episode=per_episode)))
    return path


def test_each_seeds_draws_are_what_a_fresh_env_draws_for_it_and_the_failures_are_joined_by_seed(tool, tmp_path):
    """The draws come from one env reset seed after seed; each equals a fresh env's draws for that seed alone, in
    another order, so a row's episodes and their scenes are joined right. Two reports pool their failures."""
    a = report(tmp_path, "a", failed_seeds={8, 11})
    b = report(tmp_path, "b", failed_seeds={11})
    older = json.loads(b.read_text())  # a report written before a randomisation field existed joins as well
    del older["sim_side"]["object_color"]
    b.write_text(json.dumps(older))
    out = tmp_path / "joined.json"
    result = tool.cli(["--reports", str(a), str(b), "--out", str(out), "--permutations", "50"])
    assert json.loads(out.read_text())["failure"] == result["failure"] == pytest.approx(3 / 12)
    episodes = {e["seed"]: e for e in result["episodes"]}
    assert [episodes[s]["failed"] for s in SEEDS] == [0, 1, 0, 0, 2, 0]
    env = gym.make("GraspLift-IRB120-v1", obs_mode="rgbd", randomization=SHIFT)
    try:
        for seed in reversed(SEEDS):
            env.reset(seed=seed)
            u = env.unwrapped
            fresh = {k: v[0].tolist() for k, v in u.randomization_draws.items()}
            got = episodes[seed]["draws"]
            assert got["object_xy"] == pytest.approx(u.target_object.pose.p[0, :2].tolist(), abs=1e-4)
            for key in ("rgb_object", "rgb_source_tray", "pattern_table", "contrast_ground"):
                assert got[key] == pytest.approx(fresh[key], abs=1e-4), (seed, key)
    finally:
        env.close()
    # every surface's colour distance to the object, pattern and contrast, and the object's place, are factors
    names = {r["factor"] for r in result["factors"]}
    assert {"source_tray: colour distance to the object", "table: pattern", "object: y (m)"} <= names
    for r in result["factors"]:
        assert sum(b["episodes"] for b in r["bins"]) == len(SEEDS)


def test_the_factor_the_failures_follow_ranks_first_and_a_shuffled_one_is_not_credited(tool):
    """Failures made to follow one factor: it spreads widest, its correlation is strong and its family-wise p small;
    a factor of pure noise gets a large p, even as one of many."""
    rng = np.random.default_rng(3)
    n = 200
    cause = rng.random(n)
    named = {f"noise {i}": (rng.random(n), False) for i in range(10)}
    named["cause"] = (cause, False)
    named["pattern"] = (rng.choice(["checker", "grain"], n), True)
    failed = np.stack([rng.random(n) < 0.8 * (cause < 0.3) for _ in range(3)])  # three policies, one cause
    ranked = tool.rank(named, failed, bins=4, permutations=500, seed=0)
    assert ranked[0]["factor"] == "cause" and ranked[0]["correlation"] < -0.5 and ranked[0]["p"] < 0.01
    assert ranked[0]["bins"][0]["failure"] > 0.6 and ranked[0]["bins"][-1]["failure"] == 0.0
    noise = [r for r in ranked if r["factor"].startswith("noise")]
    assert min(r["p"] for r in noise) > 0.01
    pattern = next(r for r in ranked if r["factor"] == "pattern")
    assert pattern["p"] is None and {b["bin"] for b in pattern["bins"]} == {"checker", "grain"}


@pytest.mark.parametrize(
    "what, make, says",
    [
        ("no shift", lambda t: [report(t, "a", set(), shift=None)], "its sim side ran with no shift"),
        ("no appearance", lambda t: [report(t, "a", set(), shift="light=0.5")], "drew no appearance"),
        (
            "other seeds",
            lambda t: [report(t, "a", set()), report(t, "b", set(), seeds=SEEDS[:-1])],
            "other episode seeds",
        ),
        (
            "other shift",
            lambda t: [report(t, "a", set()), report(t, "b", set(), shift="color=0.1,texture=1")],
            "another sim_side",
        ),
        (
            "other task",
            lambda t: [report(t, "a", set()), report(t, "b", set(), env_id="TableClearing-IRB120-v1")],
            "another env_id",
        ),
    ],
)
def test_reports_that_cannot_be_joined_are_one_line_and_exit_2(tool, tmp_path, capsys, what, make, says):
    paths = make(tmp_path)
    with pytest.raises(SystemExit) as e:
        tool.cli(["--reports", *map(str, paths), "--out", str(tmp_path / "x.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and says in err[0], (what, err)
    assert not (tmp_path / "x.json").exists()


def test_bins_and_permutations_are_checked(tool, tmp_path, capsys):
    path = report(tmp_path, "a", set())
    for flag, value, says in (("--bins", "1", "--bins 1: at least 2"), ("--permutations", "-1", "--permutations")):
        with pytest.raises(SystemExit) as e:
            tool.cli(["--reports", str(path), flag, value])
        assert e.value.code == 2 and says in capsys.readouterr().err
