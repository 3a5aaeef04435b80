"""Budgets in env steps: the recipes' env-step budgets are the committed runs' env steps, and learning.py hands a
run its env steps (with the minutes only as a guard) and checks an adopted run against them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import tyro

from agents import ppo
from agents.common.logging import Logger, finish
from agents.recipes import ENV_STEP_BUDGETS, RECIPES
from agents.recipes import recipe as recipe_on
from benchmarks import learning
from benchmarks.lib import budget, runner

REPO = Path(__file__).resolve().parents[2]

GL = "GraspLift-IRB120-v1"


def trained(tmp_path: Path, module, recipe: str, name: str, extra: list[str], wall_s: float, steps: int) -> Path:
    """A finished run of ``recipe``'s flags plus ``extra``, as the trainer logs and summarises it (as
    test_learning_stages.py writes one)."""
    flags = [*recipe_on(recipe, GL).argv(), "--env-id", GL, "--eval-episodes", "100", *extra]
    args = tyro.cli(module.Args, args=[*flags, "--runs-dir", str(tmp_path), "--exp-name", name, "--no-progress"])
    run_dir = tmp_path / name
    log = Logger(run_dir, args)
    log.scalars({"train/success_rate": 0.5}, steps)
    log.close()
    finish(dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=steps, wall_clock_s=wall_s), run_dir)
    return run_dir


def committed_rows() -> dict[str, dict[str, list[dict]]]:
    out = {}
    for path in (REPO / "benchmarks" / "results" / "learning").rglob("learning.json"):
        report = json.loads(path.read_text())
        out[report["env_id"]] = {
            r["recipe"]: r["runs"] for r in report["rows"] if r["recipe"] not in ("random", "expert")
        }
    return out


def test_each_env_step_budget_is_its_committed_runs_mean_env_steps_and_every_committed_row_has_one():
    rows = committed_rows()
    for env_id, recipes in rows.items():
        assert set(ENV_STEP_BUDGETS.get(env_id, {})) == set(recipes), env_id
        for recipe, runs in recipes.items():
            total, base = ENV_STEP_BUDGETS[env_id][recipe]
            assert total == round(sum(r["env_steps"] for r in runs) / len(runs)), (env_id, recipe)
            bases = [r["base"]["env_steps"] for r in runs if "base" in r]
            assert base == (round(sum(bases) / len(bases)) if bases else None), (env_id, recipe)
            assert (base is not None) == (RECIPES[recipe].base is not None)


def test_a_run_gets_its_env_steps_and_the_minutes_only_as_a_guard():
    args = learning.Args(env_id=GL, env_step_budgets=True)
    assert learning.steps_for("ppo-state", args) == (824_960, None) == recipe_on("ppo-state", GL).env_steps
    assert learning.steps_for("ppo-state", learning.Args(env_id=GL)) is None  # minutes, as the committed rows
    with pytest.raises(ValueError, match="--env-step-budgets: dagger-state has no committed runs on GraspLift"):
        learning.steps_for("dagger-state", args)
    # an explicit budget: a two-stage recipe's first stage gets the share its committed runs did
    total, base = learning.steps_for("teacher-student-rgbd", learning.Args(env_id=GL, total_env_steps=10**6))
    assert total == 10**6 and base == round(1_347_755 / 1_684_889 * 10**6)
    assert budget.budget_flags(None, 500) == ["--total-env-steps", "500"]
    assert budget.budget_flags(30.0, 500) == ["--total-env-steps", "500", "--max-minutes", "30"]
    assert budget.budget_flags(60.0, None) == ["--budget-min", "60"]


def test_a_two_stage_run_in_env_steps_gives_its_second_stage_what_the_first_left(tmp_path, monkeypatch):
    calls = []

    def fake(name, module, flags, seed, budget, args, *, env_steps=None, **kw):
        calls.append((name, budget, env_steps))
        done = env_steps + 10 if "base" in name else env_steps  # the base overshoots by part of its last step
        return dict(env_steps=done, wall_clock_s=60.0, curve=dict(env_steps=[], wall_min=[], success=[]),
                    checkpoint="b.pt", command="x", success_rate=0.5, stopped_early=False)  # fmt: skip

    monkeypatch.setattr(runner, "run_trainer", fake)
    args = learning.Args(env_id=GL, env_step_budgets=True, max_minutes=100.0, out_dir=tmp_path)
    run = learning.train_run("teacher-student-rgbd", 1, args)
    total, base = ENV_STEP_BUDGETS[GL]["teacher-student-rgbd"]
    assert calls == [
        ("teacher-student-rgbd__s1__base", 100.0, base),
        ("teacher-student-rgbd__s1", 99.0, total - base - 10),
    ]
    assert run["total_env_steps"] == total and run["env_steps"] == total and run["stopped_early"] is False


def test_an_adopted_run_is_checked_against_its_env_step_budget(tmp_path):
    args = learning.Args(recipes=["ppo-state"], seeds=[], out_dir=tmp_path, env_id=GL, env_step_budgets=True)
    good = trained(tmp_path, ppo, "ppo-state", "good", ["--total-env-steps", "824960"], 2000.0, 824_960)
    assert learning.adopted_run("ppo-state", good, args)["env_steps"] == 824_960
    other = trained(tmp_path, ppo, "ppo-state", "other", ["--total-env-steps", "500000"], 2000.0, 500_000)
    with pytest.raises(ValueError, match=r"total_env_steps=500000 \(the recipe's: 824960\)"):
        learning.adopted_run("ppo-state", other, args)
    minutes = trained(tmp_path, ppo, "ppo-state", "minutes", ["--budget-min", "36"], 2160.0, 896_000)
    # held to minutes: its env-step budget is PPO's default, not the recipe's
    with pytest.raises(ValueError, match=r"total_env_steps=100000 \(the recipe's: 824960\)"):
        learning.adopted_run("ppo-state", minutes, args)


def test_the_original_experiment_runs_its_committed_env_steps_when_asked():
    from benchmarks import original_experiment as oe

    flags = oe.command("ppo-rgbd", oe.Args(env_step_budgets=True, max_minutes=160.0), resume=False)
    at = flags.index("--total-env-steps")
    assert flags[at + 1 : at + 4] == ["967680", "--max-minutes", "160"] and "--budget-min" not in flags
    minutes = oe.command("ppo-rgbd", oe.Args(), resume=False)  # as the committed runs were started
    assert minutes[minutes.index("--budget-min") + 1] == "150" and "--total-env-steps" not in minutes
    assert oe.budget_text(oe.Args(total_env_steps=10**6)) == "1,000,000 env steps"
    assert "--curve-points" not in minutes  # a held-out curve needs an env-step budget to take its shares of


def test_the_report_scale_runs_take_the_fast_update_and_a_held_out_curve():
    """Issue 92's 4M-step runs: ppo-rgbd at the fast camera update, with held-out success every tenth."""
    from agents.recipes import PPO_CAMERA_FAST
    from benchmarks import original_experiment as oe

    flags = oe.command("ppo-rgbd-fast", oe.Args(recipes=["ppo-rgbd-fast"], total_env_steps=4_000_000), resume=False)
    for flag, value in PPO_CAMERA_FAST.items():
        assert flags[flags.index(f"--{flag}") + 1] == str(value)
    assert flags[flags.index("--curve-points") + 1] == "10" and "--absorbing-success" in flags
    dense = oe.command("ppo-rgbd-dense-fast", oe.Args(total_env_steps=10), resume=False)
    assert dense[dense.index("--reward-mode") + 1] == "dense" and "--absorbing-success" not in dense
    with pytest.raises(ValueError, match="unknown recipes \\['ppo-state'\\]"):
        oe.check(oe.Args(recipes=["ppo-state"]))
