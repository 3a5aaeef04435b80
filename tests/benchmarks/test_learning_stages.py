"""Two-stage recipes (a base run whose checkpoint the second stage starts from or imitates) adopted from runs trained
by the trainers' own commands, as teacher-student-rgbd is across sessions."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
import tyro

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))

import learning  # noqa: E402

from agents import dagger, ppo  # noqa: E402
from agents.common.logging import Logger, finish  # noqa: E402

ENV = "GraspLift-IRB120-v1"


def trained(
    tmp_path: Path, module, recipe: str, name: str, extra: list[str], wall_s: float, steps: int, env: str = ENV
) -> Path:
    """A finished run of ``recipe``'s flags plus ``extra``, as the trainer logs and summarises it."""
    flags = [*learning.recipe_flags(recipe, env), "--env-id", env, "--eval-episodes", "100", *extra]
    args = tyro.cli(module.Args, args=[*flags, "--runs-dir", str(tmp_path), "--exp-name", name, "--no-progress"])
    run_dir = tmp_path / name
    log = Logger(run_dir, module.resolved(args) if hasattr(module, "resolved") else args)
    log.scalars({"train/success_rate": 0.5}, steps)
    log.close()
    ckpt = str(run_dir / "checkpoints" / "best.pt")
    finish(
        dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=steps, wall_clock_s=wall_s, checkpoint=ckpt), run_dir
    )
    return run_dir


def test_a_teacher_and_its_student_join_the_row_as_one_run(tmp_path):
    args = learning.Args(recipes=["teacher-student-rgbd"], seeds=[], out_dir=tmp_path, env_id=ENV)
    budget = learning.VISION_BUDGET_MIN[ENV]
    share = learning.BASES["teacher-student-rgbd"][1]
    teacher = trained(tmp_path, ppo, "ppo-state", "teacher", ["--budget-min", f"{share * budget:.4g}"], 2700.0, 10**6)
    ckpt = str(teacher / "checkpoints" / "best.pt")
    rest = f"{budget - 45:.4g}"
    student = trained(
        tmp_path, dagger, "teacher-student-rgbd", "student", ["--teacher", ckpt, "--budget-min", rest], 4500.0, 10**5
    )
    run = learning.adopted_pair("teacher-student-rgbd", teacher, student, args)
    assert run["env_steps"] == 10**6 + 10**5 and run["wall_clock_s"] == 7200.0
    assert run["base"]["checkpoint"] == ckpt and run["base"]["env_steps"] == 10**6
    assert f"--teacher {ckpt}" in run["command"] and run["adopted_from"] == f"{teacher} + {student}"
    # the results table shows each stage on its own line: the teacher's own held-out success, steps and minutes
    row = dict(recipe="teacher-student-rgbd", runs=[dict(run, seed=7)])
    assert learning.stage_lines([row]).splitlines()[-1] == (
        "- seed 7: ppo-state 0.90, 1,000,000, 45.0; then teacher-student-rgbd 0.90, 100,000, 75.0"
    )
    assert learning.stage_lines([dict(recipe="ppo-state", runs=[dict(seed=7, success_rate=0.5)])]) == ""  # one stage
    # a student of another teacher, or one that trained longer than the budget left it, is not this recipe's
    other = trained(
        tmp_path, dagger, "teacher-student-rgbd", "other", ["--teacher", "x.pt", "--budget-min", rest], 4500.0, 10**5
    )
    with pytest.raises(ValueError, match=r"teacher=.*x\.pt"):
        learning.adopted_pair("teacher-student-rgbd", teacher, other, args)
    longer = trained(
        tmp_path, dagger, "teacher-student-rgbd", "longer", ["--teacher", ckpt, "--budget-min", "90"], 5400.0, 10**5
    )
    with pytest.raises(ValueError, match=r"budget_min=90\.0"):
        learning.adopted_pair("teacher-student-rgbd", teacher, longer, args)
    with pytest.raises(ValueError, match="--adopt-base"):
        learning.adopted_run("teacher-student-rgbd", student, args)


def test_the_selecting_teacher_student_gives_its_teacher_a_tasks_own_share(tmp_path):
    """teacher-student-rgbd-sel: on TableClearing the teacher gets 0.6 of the 150 min (90) and the student, which
    selects on 30 validation seeds, the rest; GraspLift keeps the 0.375 of BASES. A TableClearing teacher trained
    for the old share is not this recipe's."""
    from maniskill_irb120.recipes import base_share

    tc = "TableClearing-IRB120-v1"
    assert base_share("teacher-student-rgbd-sel", tc) == 0.6 and base_share("teacher-student-rgbd", tc) == 0.375
    assert base_share("teacher-student-rgbd-sel", ENV) == 0.375
    student_flags = learning.recipe_flags("teacher-student-rgbd-sel", tc)
    assert student_flags[student_flags.index("--select-episodes") + 1] == "30"
    args = learning.Args(recipes=["teacher-student-rgbd-sel"], seeds=[], out_dir=tmp_path, env_id=tc)
    teacher = trained(tmp_path, ppo, "ppo-state", "teacher", ["--budget-min", "90"], 5400.0, 10**6, env=tc)
    ckpt = str(teacher / "checkpoints" / "best.pt")
    student = trained(
        tmp_path, dagger, "teacher-student-rgbd-sel", "student", ["--teacher", ckpt, "--budget-min", "60"],
        3600.0, 10**5, env=tc,
    )  # fmt: skip
    run = learning.adopted_pair("teacher-student-rgbd-sel", teacher, student, args)
    assert run["wall_clock_s"] == 9000.0 and run["base"]["wall_clock_s"] == 5400.0
    old = trained(tmp_path, ppo, "ppo-state", "old-teacher", ["--budget-min", "56.25"], 3375.0, 10**6, env=tc)
    with pytest.raises(ValueError, match=r"budget_min=56\.25 \(the recipe's: 90\.0\)"):
        learning.adopted_pair("teacher-student-rgbd-sel", old, student, args)


def test_the_original_experiment_resumes_and_reads_the_report_figures_from_the_logs(tmp_path):
    """A run with a checkpoint is resumed, a finished one skipped; the figures are the runs' per-episode reward terms,
    and the episode reward is the report's (the sum of its terms) whatever reward the run trained on."""
    import original_experiment as oe

    args = oe.Args(runs_dir=tmp_path, out_dir=tmp_path)
    assert "--resume" not in oe.command("ppo-rgbd-dense", args)
    latest = oe.run_dir("ppo-rgbd-dense", args) / "checkpoints" / "latest.pt"
    latest.parent.mkdir(parents=True)
    latest.write_bytes(b"")
    cmd = oe.command("ppo-rgbd-dense", args)
    assert cmd[cmd.index("--resume") + 1] == str(latest) and cmd[cmd.index("--reward-mode") + 1] == "dense"
    (oe.run_dir("ppo-rgbd", args)).mkdir(parents=True)
    (oe.run_dir("ppo-rgbd", args) / "summary.json").write_text("{}")
    assert oe.train("ppo-rgbd", args, deadline=None) == "done"
    # past the deadline (the run before took the session's share) nothing starts: no process, no log
    assert oe.train("ppo-rgbd-dense", args, deadline=time.time() - 1) == "not started"
    assert not (args.runs_dir / "logs").exists()
    log = Logger(oe.run_dir("ppo-rgbd-dense", args), ppo.Args())
    terms = dict(r_collision=[-1000.0, 0.0], r_grasp=[0.0, 100.0], r_drop=[0.0, 0.0], r_time=[-5.0, -3.0])
    for i, step in enumerate((512, 1024)):
        log.scalars({f"train/return_{k}": v[i] for k, v in terms.items()}, step)
    log.close()
    fig = oe.figures(oe.scalars(oe.run_dir("ppo-rgbd-dense", args)))
    assert fig["env_steps"] == [512, 1024] and fig["r_collision"] == [-1000.0, 0.0] and fig["r_grasp"] == [0.0, 100.0]
    assert fig["episode_reward"] == [-1005.0, 97.0]
    # each figure gets its optimum line; the captions' values but Figure 5.4's (see OPTIMA_NOTE)
    assert [optimum for _, _, optimum in oe.FIGURES] == [0.0, 100.0, 0.0, 200.0]
    # a long run's curve is kept as the means of consecutive points, each at its last env step
    many = {"train/return_r_grasp": [(512 * (i + 1), float(i)) for i in range(10)]}
    thin = oe.figures(many, points=4)  # runs of 3, 3, 2 and 2 points
    assert thin["env_steps"] == [1536, 3072, 4096, 5120] and thin["r_grasp"] == [1.0, 4.0, 6.5, 8.5]
    assert thin["episode_reward"] == thin["r_grasp"] and thin["r_collision"] == [0.0] * 4
    assert oe.figures(many, points=10)["r_grasp"] == [float(i) for i in range(10)]  # short enough: every point


@pytest.mark.slow
def test_the_original_experiment_trains_resumes_and_plots(tmp_path):
    """benchmarks/original_experiment.py at toy size: both runs train, a second call finds them finished, and the
    figures come from the runs' logs (the report's reward terms against env steps)."""
    import json
    import subprocess

    cmd = [sys.executable, str(REPO / "benchmarks" / "original_experiment.py"), "--quick"]
    cmd += ["--runs-dir", str(tmp_path / "runs"), "--out-dir", str(tmp_path)]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    report = json.loads((tmp_path / "original_experiment.json").read_text())
    assert report["status"] == {"ppo-rgbd-dense": "done", "ppo-rgbd": "done"}
    for recipe, row in report["runs"].items():
        assert row["finished"] and row["env_steps"] > 0 and 0.0 <= row["success_rate"] <= 1.0, recipe
        assert "--obs rgbd" in row["command"] and ("--reward-mode dense" in row["command"]) == recipe.endswith("dense")
    assert (tmp_path / "original_experiment.png").stat().st_size > 1000
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "[original] " not in again.stdout  # nothing left to train
