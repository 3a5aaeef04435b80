"""benchmarks/algorithms.py: one cell at toy size end to end (JSON, PNG, RESULTS.md section), a rerun that skips
finished cells and continues a checkpointed one with the rest of its budget, and the cell plan (the best cell's
extra seeds, --only)."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import signal
import sys
from pathlib import Path

import pytest

from benchmarks.lib import runner
from maniskill_irb120.vector import TORCH_THREADS


@pytest.fixture(scope="module")
def alg(bench_script):
    return bench_script("algorithms")


def results_md(tmp_path: Path) -> Path:
    md = tmp_path / "RESULTS.md"
    md.write_text("# Results\n\n## Earlier\n\nkept\n\n## Later\n\nkept too\n")
    return md


def test_one_cell_writes_the_json_png_and_section_and_a_rerun_skips_it(alg, tmp_path):
    pytest.importorskip("stable_baselines3")
    md = results_md(tmp_path)
    cell = "state/GraspLift/sb3-ppo/s1"
    args = alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs", num_envs=2, quick=True,
                    update_results=True, results_md=md)  # fmt: skip
    report = alg.main(args)
    data = json.loads((tmp_path / "algorithms.json").read_text())
    assert list(data["cells"]) == [cell]
    one = data["cells"][cell]
    assert one["env_steps"] > 0 and 0 < one["wall_clock_s"] < 60 and len(one["successes"]) == 2
    assert 0.0 <= one["cpu_steal"] < 1.0  # the share of CPU time the host took while it trained (Linux)
    assert one["torch_threads"] == TORCH_THREADS  # the library learner's count, recorded
    assert len(one["reference_sps"]) == 2 and min(one["reference_sps"]) > 0  # the machine's speed before and after
    assert one["budget_min"] == 0.05 and (tmp_path / "runs" / "state__GraspLift__sb3-ppo__s1" / "model.zip").is_file()
    row = next(r for r in data["rows"] if (r["obs"], r["task"], r["algorithm"]) == ("state", "GraspLift", "sb3-ppo"))
    lo, hi = row["success_ci95"]
    assert row["seeds"] == [1] and row["interval"] == "Wilson" and 0 <= lo <= row["success_mean"] <= hi <= 1
    assert data["versions"]["stable_baselines3"] == "2.9.2" and "RHPO" in data["not_runnable"]
    assert len(data["rows"]) == len(alg.grid()) == 35 and sum("success_mean" in r for r in data["rows"]) == 1  # pending
    assert (tmp_path / "algorithms.png").stat().st_size > 5000
    text = md.read_text()
    assert text.count(alg.SECTION_HEAD) == 1 and "## Earlier\n\nkept\n" in text and "## Later\n\nkept too" in text
    section = text[text.index(alg.SECTION_HEAD) :]
    assert "| state | GraspLift | PPO | Stable-Baselines3 2.9.2 | 1 |" in section and "| RHPO |" in section
    assert "pending" in section and "](algorithms.png)" in section and report["rows"] == data["rows"]
    ref = row["reference_sps_mean"]
    assert f"| {ref[0]:.0f} / {ref[1]:.0f} |" in section and "reference env steps/s, before / after" in section
    assert f"Last run: `{report['command']}`" in section and f"({one['date']} to {one['date']})" in section
    # a rerun finds the cell done and runs nothing (its date stays)
    again = alg.main(args)
    assert again["cells"][cell]["date"] == one["date"] and md.read_text().count(alg.SECTION_HEAD) == 1


@pytest.mark.slow  # two cells' worker start-ups and evaluations (~17 s)
def test_a_checkpointed_cell_continues_with_the_rest_of_its_budget(alg, tmp_path, capsys):
    """A session that ended inside a cell leaves its checkpoint and no result: the rerun loads the agent, counts on
    from its env steps and curve, and stops when the earlier session's time plus its own reach the budget."""
    pytest.importorskip("skrl")
    cell, name = "state/GraspLift/skrl-ppo/s1", "state__GraspLift__skrl-ppo__s1"
    args = alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs", num_envs=2, quick=True)
    args.quick, args.budget_min, args.eval_episodes, args.checkpoint_min, args.bootstrap = False, 0.02, 1, 1.0, 50
    first = alg.main(args)["cells"][cell]
    (tmp_path / "algorithms.json").unlink()  # as if the session had ended before the cell's result was written
    args.budget_min = 0.06
    out = alg.main(args)["cells"][cell]
    assert f"continuing from {tmp_path / 'runs' / name / 'agent.pt'}" in capsys.readouterr().out
    assert out["env_steps"] > first["env_steps"]
    assert 0.06 * 60 <= out["wall_clock_s"] < 0.06 * 60 + 15


@pytest.mark.slow  # two cells' worker start-ups and one evaluation (~25 s)
def test_sigterm_inside_a_library_cell_saves_what_a_rerun_continues_from(alg, tmp_path, monkeypatch, capsys):
    """A session stopped with SIGTERM (``kill``, the end of a session) mid-cell: the cell saves its model and clock
    there and then, not only at its periodic checkpoint, the benchmark exits 130, and the rerun continues it."""
    pytest.importorskip("stable_baselines3")
    cell, name = "state/GraspLift/sb3-ppo/s1", "state__GraspLift__sb3-ppo__s1"
    args = alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs", num_envs=2, reference_steps=0)
    args.budget_min, args.eval_episodes, args.checkpoint_min, args.bootstrap = 0.05, 1, 100.0, 50  # no periodic save
    save_due = alg.Budget.save_due
    sent = []

    def terminated(self):  # asked from inside SB3's learn, after each vector step
        if not sent:
            sent.append(self.spent_s)
            os.kill(os.getpid(), signal.SIGTERM)
        return save_due(self)

    monkeypatch.setattr(alg.Budget, "save_due", terminated)
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stop:
        alg.main(args)
    assert stop.value.code == 130 and signal.getsignal(signal.SIGTERM) is before  # pytest's own handler is back
    assert f"{cell}: interrupted; the same command continues it" in capsys.readouterr().out
    run = tmp_path / "runs" / name
    saved = json.loads((run / "state.json").read_text())
    assert (run / "model.zip").is_file() and saved["env_steps"] >= 2 and saved["spent_s"] >= sent[0] > 0
    assert not (tmp_path / "algorithms.json").exists()  # no result for a cell that did not finish
    monkeypatch.setattr(alg.Budget, "save_due", save_due)
    out = alg.main(args)["cells"][cell]
    assert f"continuing from {run / 'model.zip'}" in capsys.readouterr().out
    assert out["env_steps"] > saved["env_steps"] and 0.05 * 60 <= out["wall_clock_s"] < 0.05 * 60 + 15


def test_render_only_derives_the_rows_again_from_the_committed_cells(alg, tmp_path):
    """A settings text mended after its cells ran reaches algorithms.json's rows and RESULTS.md with --render-only,
    and every measured figure (success, interval, steps, reference) comes out as the cells gave it."""
    committed = json.loads((alg.ROOT / "benchmarks" / "results" / "algorithms.json").read_text())
    stale = json.loads(json.dumps(committed))
    for row in stale["rows"]:
        row["settings"] = "an old text"
    (tmp_path / "algorithms.json").write_text(json.dumps(stale))
    md = results_md(tmp_path)
    report = alg.main(alg.Args(render_only=True, out_dir=tmp_path, results_md=md))
    again = json.loads((tmp_path / "algorithms.json").read_text())
    assert again == report and again["cells"] == committed["cells"]
    assert [r["settings"] for r in again["rows"]] == [alg.settings_of(r["obs"], r["algorithm"]) for r in again["rows"]]
    measured = ("success_mean", "success_ci95", "per_seed", "env_steps_mean", "reference_sps_mean", "seeds")
    rows = {(r["obs"], r["task"], r["algorithm"]): r for r in again["rows"]}  # rows added since stay pending
    assert [{k: rows[r["obs"], r["task"], r["algorithm"]].get(k) for k in measured} for r in committed["rows"]] == [
        {k: r.get(k) for k in measured} for r in committed["rows"]
    ]
    assert "an old text" not in md.read_text() and alg.ALGORITHMS["skrl-ppo"].settings in md.read_text()


def test_another_folders_table_leaves_the_results_section_alone(alg, tmp_path, capsys):
    """RESULTS.md's "RL libraries" section is the table of benchmarks/results/; screening, full-budget and probe
    folders have sections of their own, so --render-only of one renders its JSON and plots and leaves RESULTS.md as
    it is, and --update-results with one is refused in one line before anything runs."""
    committed = (alg.ROOT / "benchmarks" / "results" / "algorithms.json").read_text()
    (tmp_path / "algorithms.json").write_text(committed)
    before = alg.Args.results_md.read_text()
    alg.main(alg.Args(render_only=True, out_dir=tmp_path))
    assert alg.Args.results_md.read_text() == before and (tmp_path / "algorithms_curves.png").is_file()
    assert "so it is left as it is" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--update-results writes RESULTS.md's 'RL libraries"):
        alg.check(alg.Args(update_results=True, out_dir=tmp_path / "probe"))
    alg.check(alg.Args(update_results=True))  # the table's own folder
    alg.check(alg.Args(update_results=True, out_dir=tmp_path, results_md=results_md(tmp_path)))  # a test's file


def test_the_plan_adds_the_best_cells_seeds_once_its_group_is_in(alg):
    args = alg.Args()
    done: dict[str, dict] = {}
    first = alg.planned(done, args)
    assert len(first) == len(alg.grid()) == 35 and all(c.endswith("/s1") for c in first)
    group = [c for c in first if c.startswith("state/GraspLift/")]
    for i, cell in enumerate(group):
        done[cell] = {"success_rate": {"sb3-sac": 0.4, "project-ppo": 0.3}.get(cell.split("/")[2], 0.1 * i / 10)}
    plan = alg.planned(done, args)
    assert "state/GraspLift/sb3-sac/s2" in plan and "state/GraspLift/sb3-sac/s3" in plan
    # the ablation row, outside the defaults rule, is never a group's best, however it scores
    done["state/GraspLift/sb3-ppo-maniskill/s1"] = {"success_rate": 0.9}
    assert alg.best_algo(done, "state", "GraspLift") == "sb3-sac"
    assert not any(c.startswith("state/TableClearing/") and not c.endswith("/s1") for c in plan)
    # a group where nothing solved a held-out episode names no best (not the last name in the alphabet)
    for cell in (c for c in first if c.startswith("state/TableClearing/")):
        done[cell] = {"success_rate": 0.0}
    assert alg.best_algo(done, "state", "TableClearing") is None
    assert not any(c.startswith("state/TableClearing/") for c in alg.planned(done, args))
    # a tie above 0 goes to the earlier algorithm in the grid
    done["state/TableClearing/sb3-td3/s1"] = done["state/TableClearing/skrl-ppo/s1"] = {"success_rate": 0.2}
    assert alg.best_algo(done, "state", "TableClearing") == "sb3-td3"
    # every camera cell learns from the reward alone (the project's is teacher-student-rgbd): the best one gets seeds
    for algo, rate in (("sb3-ppo", 0.1), ("sb3-sac", 0.2), ("project-camera", 0.9), ("sb3-ppo-tuned", 0.3)):
        done[f"rgbd/GraspLift/{algo}/s1"] = {"success_rate": rate}
    assert alg.best_algo(done, "rgbd", "GraspLift") == "project-camera"
    args.only = ["rgbd/*"]
    assert alg.planned(done, args) == ["rgbd/GraspLift/project-camera/s2", "rgbd/GraspLift/project-camera/s3"]
    # --seeds: more seeds of the --only cells, their group's best or not (the targets want 3 seeds of several)
    args.only, args.seeds = ["state/GraspLift/project-ppo/*"], [2, 3]
    done["state/GraspLift/project-ppo/s2"] = {"success_rate": 0.5}
    assert alg.planned(done, args) == ["state/GraspLift/project-ppo/s3"]
    args.only = ["state/GraspLift/sb3-sac/*"]  # the best's seeds, named by both rules, run once
    assert alg.planned(done, args) == ["state/GraspLift/sb3-sac/s2", "state/GraspLift/sb3-sac/s3"]
    alg.check(alg.Args(only=["*/project-ppo/s4"], seeds=[4]))  # a seed --seeds adds is a known cell
    for bad, match in ((dict(seeds=[2]), "name them with --only"), (dict(only=["*"], seeds=[0]), "numbered from 1")):
        with pytest.raises(ValueError, match=match):
            alg.check(alg.Args(**bad))


@pytest.mark.slow  # two runs of one cell: worker start-ups and evaluations (~40 s)
def test_the_ablation_cell_trains_sb3_ppo_with_maniskills_settings_on_normalised_observations(alg, tmp_path, capsys):
    """The ablation's SB3 PPO gets the settings its row prints, trains on VecNormalize's observations and keeps the
    running statistics beside the model, which the held-out evaluation needs; a rerun of an unfinished cell goes on
    from those statistics, not from fresh ones."""
    pytest.importorskip("stable_baselines3")
    import pickle

    from stable_baselines3 import PPO

    def statistics(run: Path):
        with open(run / "vecnormalize.pkl", "rb") as f:
            return pickle.load(f)

    cell = "state/GraspLift/sb3-ppo-maniskill/s1"
    args = alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs", num_envs=2, quick=True)
    report = alg.main(args)
    run = tmp_path / "runs" / "state__GraspLift__sb3-ppo-maniskill__s1"
    model = PPO.load(run / "model.zip", device="cpu")
    assert (model.gamma, model.gae_lambda, model.target_kl) == (0.8, 0.9, 0.1)
    assert (model.n_steps, model.batch_size, model.n_epochs) == (128, 64, 8)
    assert model.policy.net_arch == dict(pi=[256] * 3, vf=[256] * 3) and model.policy.log_std.detach().max() < 0
    norm = statistics(run)
    assert norm.norm_obs and not norm.norm_reward and norm.obs_rms.count > 2  # updated by the training steps
    assert len(report["cells"][cell]["successes"]) == 2
    row = next(r for r in report["rows"] if r["algorithm"] == "sb3-ppo-maniskill")
    assert row["name"].endswith("(ablation)") and "VecNormalize" in row["settings"]
    # as if the session had ended inside the cell: the rerun continues the model and its statistics
    (tmp_path / "algorithms.json").unlink()
    args.budget_min = 0.1
    alg.main(args)
    assert f"continuing from {run / 'model.zip'}" in capsys.readouterr().out
    steps = json.loads((run / "state.json").read_text())["env_steps"]  # both runs' (SB3 counts on when resumed)
    assert steps > norm.obs_rms.count and statistics(run).obs_rms.count >= steps  # every env step's observation


def test_bad_cells_and_backends_are_named(alg, tmp_path):
    with pytest.raises(ValueError, match="--only 'state/Stack/\\*' matches no cell"):
        alg.main(alg.Args(only=["state/Stack/*"], out_dir=tmp_path))
    with pytest.raises(ValueError, match="unknown backend 'tpu'"):
        alg.main(alg.Args(backend="tpu", out_dir=tmp_path))
    with pytest.raises(ValueError, match="--reference-steps must be >= 0"):
        alg.main(alg.Args(reference_steps=-1, out_dir=tmp_path))


def test_wilson_interval(alg):
    lo, hi = alg.wilson(50, 100)
    assert lo == pytest.approx(0.4038, abs=1e-4) and hi == pytest.approx(0.5962, abs=1e-4)
    assert alg.wilson(0, 100)[0] == 0.0 and alg.wilson(100, 100)[1] == 1.0


def test_the_camera_cell_trains_a_state_teacher_then_its_camera_student_within_one_budget(alg, tmp_path, monkeypatch):
    """teacher-student-rgbd from the reward alone: the teacher (ppo-state) in its share, the student handed its
    checkpoint in the rest; the cell counts both stages, and a stage finished in an earlier session is not rerun."""
    calls = []

    def fake_trainer(cmd, **kwargs):
        flags = cmd[3:]
        name = flags[flags.index("--exp-name") + 1]
        budget = float(flags[flags.index("--budget-min") + 1])
        calls.append((cmd[2], name, budget, flags))
        wall = 60 * budget * 0.9
        result = dict(
            success_rate=0.5, successes=[1, 0], env_steps=1000, wall_clock_s=wall, checkpoint=f"/ckpt/{name}.pt"
        )
        line = json.dumps(result)
        return type("P", (), dict(returncode=0, communicate=lambda self, timeout=None: (line + "\n", "")))()

    monkeypatch.setattr(runner.subprocess, "Popen", fake_trainer)  # runner.run_trainer runs it
    args = alg.Args(out_dir=tmp_path, runs_dir=tmp_path / "runs")
    assert (
        alg.ALGORITHMS["project-camera"].from_reward
        and alg.ALGORITHMS["project-camera"].recipe == "teacher-student-rgbd"
    )
    for stage in ("cell__base", "cell"):
        (tmp_path / "runs" / "project" / stage).mkdir(parents=True)
    r = alg.run_project("teacher-student-rgbd", "GraspLift-IRB120-v1", 1, 60.0, "cell", args)
    (teacher, t_name, t_budget, _), (student, s_name, s_budget, s_flags) = calls
    assert (teacher, t_name, t_budget) == ("agents.ppo", "cell__base", 22.5)  # 0.375 of 60 min
    assert student == "agents.dagger" and s_name == "cell" and "--obs" in s_flags
    assert s_flags[s_flags.index("--teacher") + 1] == "/ckpt/cell__base.pt"
    assert s_budget == pytest.approx(60 - 22.5 * 0.9, abs=1e-3)  # the rest of the budget after the teacher's time
    assert r["env_steps"] == 2000 and r["wall_clock_s"] == pytest.approx(60 * (22.5 + s_budget) * 0.9)
    assert r["base"]["checkpoint"] == "/ckpt/cell__base.pt"
    calls.clear()
    (tmp_path / "runs" / "project" / "cell" / "stage.json").unlink()  # the student was cut short: only it runs again
    alg.run_project("teacher-student-rgbd", "GraspLift-IRB120-v1", 1, 60.0, "cell", args)
    assert [c[1] for c in calls] == ["cell"]


# ~45-90 s: an SB3 SAC cell's worker start-ups and held-out episodes; the selection-callback test trains a cell in env
# steps and checks the budget it records, test_the_default_budgets_are_env_steps_and_a_zero_one_is_refused the rest
@pytest.mark.slow
def test_a_cell_budgeted_in_env_steps_trains_them_and_records_its_budget(alg, tmp_path):
    """SB3 counts the cell's env steps itself (learn's total_timesteps): the cell stops at its budget, not on a clock,
    and records the budget, no guard, and that nothing stopped it early."""
    pytest.importorskip("stable_baselines3")
    cell = "state/GraspLift/sb3-sac/s1"
    args = alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs", num_envs=2, quick=True,
                    total_env_steps=40, reference_steps=0)  # fmt: skip
    report = alg.main(args)
    one = report["cells"][cell]
    assert one["env_steps"] == 40 and one["total_env_steps"] == 40 and one["stopped_early"] is False
    assert one["max_minutes"] is None and "budget_min" not in one
    row = next(r for r in report["rows"] if r["algorithm"] == "sb3-sac" and r["task"] == "GraspLift")
    assert row["total_env_steps"] == 40
    pending = next(r for r in report["rows"] if r["algorithm"] == "sb3-td3" and r["task"] == "TableClearing")
    assert pending["total_env_steps"] == 40 and "(40 env steps budget)" in alg.markdown(report["rows"])


def test_the_default_budgets_are_env_steps_and_a_zero_one_is_refused(alg, tmp_path):
    """The default budgets are issue 91's, per task and observation."""
    default = alg.Args()
    assert alg.steps_of("state", "GraspLift", default) == 500_000 and alg.steps_of("state", "TableClearing", default)
    assert alg.steps_of("rgbd", "GraspLift", default) == 1_000_000 and alg.minutes_of(default) is None
    assert alg.steps_of("state", "GraspLift", alg.Args(budget_min=30.0)) is None  # a cell in minutes, as before
    with pytest.raises(ValueError, match="--total-env-steps must be positive, got 0"):
        alg.main(alg.Args(total_env_steps=0, out_dir=tmp_path))


def test_the_project_cell_in_env_steps_has_its_trainer_take_the_held_out_curve(alg, tmp_path, monkeypatch):
    """A one-stage project cell (the project's PPO) in env steps asks its trainer for the held-out curve
    (--curve-points, --curve-episodes: the trainer's own loop takes it), and the cell's held_out_curve is the
    trainer's points then its final evaluation, as a library cell's."""
    calls = []

    def fake_trainer(cmd, **kwargs):
        flags = cmd[3:]
        calls.append(flags)
        held = [[100, 1.0, 0.0, [0, 0], 3.0], [250, 2.0, 0.5, [1, 0], 3.0]]
        result = dict(success_rate=0.75, successes=[1, 1, 1, 0], env_steps=1000, wall_clock_s=600.0,
                      checkpoint="/c.pt", held_out_curve=held)  # fmt: skip
        line = json.dumps(result)
        return type("P", (), dict(returncode=0, communicate=lambda self, timeout=None: (line + "\n", "")))()

    monkeypatch.setattr(runner.subprocess, "Popen", fake_trainer)
    args = alg.Args(out_dir=tmp_path, runs_dir=tmp_path / "runs", curve_points=4, curve_episodes=2)
    (tmp_path / "runs" / "project" / "cell").mkdir(parents=True)
    r = alg.run_project("ppo-state", "GraspLift-IRB120-v1", 1, None, "cell", args, 1000)
    (flags,) = calls
    assert flags[flags.index("--curve-points") + 1] == "4" and flags[flags.index("--curve-episodes") + 1] == "2"
    curve = r["held_out_curve"]
    assert curve["env_steps"] == [100, 250, 1000] and curve["success"] == [0.0, 0.5, 0.75]
    assert curve["episodes"] == [2, 2, 4] and curve["eval_s"] == [3.0, 3.0, None]
    # the table reads the trainer's point at a quarter of the budget, and the final evaluation at the end
    assert alg.held_out_at([dict(r, total_env_steps=1000)]) == {"0.25": 0.5, "0.5": None, "1": 0.75}


def test_the_camera_cell_in_env_steps_gives_its_teacher_the_committed_share(alg, tmp_path, monkeypatch):
    calls = []

    def fake_trainer(cmd, **kwargs):
        flags = cmd[3:]
        name = flags[flags.index("--exp-name") + 1]
        steps = int(flags[flags.index("--total-env-steps") + 1])
        calls.append((name, steps, "--budget-min" in flags, flags[flags.index("--max-minutes") + 1]))
        result = dict(success_rate=0.5, successes=[1, 0], env_steps=steps, wall_clock_s=600.0, checkpoint="/c.pt")
        line = json.dumps(result)
        return type("P", (), dict(returncode=0, communicate=lambda self, timeout=None: (line + "\n", "")))()

    monkeypatch.setattr(runner.subprocess, "Popen", fake_trainer)
    args = alg.Args(out_dir=tmp_path, runs_dir=tmp_path / "runs", max_minutes=60.0)
    for stage in ("cell__base", "cell"):
        (tmp_path / "runs" / "project" / stage).mkdir(parents=True)
    r = alg.run_project("teacher-student-rgbd", "GraspLift-IRB120-v1", 1, 60.0, "cell", args, 10**6)
    from agents.recipes import ENV_STEP_BUDGETS

    total, base = ENV_STEP_BUDGETS["GraspLift-IRB120-v1"]["teacher-student-rgbd"]
    teacher_steps = round(base / total * 10**6)
    assert calls == [("cell__base", teacher_steps, False, "60"), ("cell", 10**6 - teacher_steps, False, "50")]
    assert r["env_steps"] == 10**6


# ----------------------------------------------------------------------------- agents/configs' tuned settings
CONFIG_EXEMPT = {"policy", "class", "name", "input", "output", "separate", "seed"}
"""keys every config of its kind carries whatever its values (rl-zoo3's policy, the skrl runner's structure)"""


def uncommented_keys(path: Path) -> list[str]:
    """The ``key: value`` lines of a YAML config without a ``# why`` comment, but for structural keys and a
    wrapper's keywords (the wrapper's own line says why)."""
    out, in_wrapper = [], None
    for line in path.read_text().splitlines():
        body = line.split("#", 1)[0].rstrip()
        indent = len(line) - len(line.lstrip())
        if not body.strip() or line.lstrip().startswith("#"):
            continue
        if in_wrapper is not None and indent > in_wrapper:
            continue
        in_wrapper = indent if body.strip().startswith("- ") and body.endswith(":") else None
        key = body.strip().lstrip("- ").split(":", 1)[0]
        scalar = ":" in body and body.split(":", 1)[1].strip() != ""  # a setting, not a section's head
        if scalar and indent > 0 and key not in CONFIG_EXEMPT and "#" not in line and in_wrapper is None:
            out.append(f"{path.name}: {line.strip()}")
    return out


def test_every_config_loads_for_both_tasks_and_every_setting_says_why_and_differs_from_the_default(alg):
    import inspect

    pytest.importorskip("sb3_contrib")
    from skrl.agents.torch.ppo import PPO_CFG
    from skrl.agents.torch.sac import SAC_CFG

    from agents.configs import loader
    from maniskill_irb120.integrations.skrl import SelectOnValidation as SkrlSelect
    from maniskill_irb120.integrations.wrappers import AbsorbingSuccess, ActionPenalty

    for algo in loader.SB3_ALGOS:
        assert uncommented_keys(loader.sb3_path(algo)) == []
        params = inspect.signature(loader.sb3_class(algo).__init__).parameters
        for env_id in alg.TASKS.values():
            cfg = loader.sb3_config(algo, env_id)
            assert (
                cfg.n_envs == 4
                and cfg.policy == "MlpPolicy"
                and cfg.normalize == {"norm_obs": True, "norm_reward": False}
            )
            assert cfg.n_timesteps == alg.STATE_ENV_STEPS[env_id.split("-")[0]]
            for key, value in cfg.kwargs.items():  # a model argument, and not its default (which needs no line)
                assert key in params and params[key].default != value, (algo, key)
            # the absorbing value at the learner's discount; the deterministic actors add the action cost
            expected = [AbsorbingSuccess, ActionPenalty] if algo in ("td3", "ddpg") else [AbsorbingSuccess]
            assert [w.func for w in cfg.wrappers] == expected, (algo, env_id)
            assert cfg.wrappers[0].keywords["gamma"] == cfg.kwargs["gamma"]
            assert ("action_noise" in cfg.model_kwargs(5)) == (algo in ("td3", "ddpg"))
    defaults = {"ppo": PPO_CFG(), "sac": SAC_CFG()}
    for algo in loader.SKRL_ALGOS:
        for env_id in alg.TASKS.values():
            path = loader.skrl_path(algo, env_id)
            assert uncommented_keys(path) == []
            cfg = loader.skrl_config(algo, env_id)
            num_envs, wrappers = loader.skrl_env_settings(cfg)
            assert num_envs == 4 and wrappers[0].keywords["gamma"] == cfg["agent"]["discount_factor"]
            assert cfg["trainer"]["timesteps"] * num_envs == alg.STATE_ENV_STEPS[env_id.split("-")[0]]
            for key, value in cfg["agent"].items():
                if key != "class":
                    default = getattr(defaults[algo], key)  # a key skrl does not know fails here, not silently
                    assert default != value, (path.name, key)
            # the project's sections never reach skrl's runner; PPO selects its checkpoint, as the SB3 PPO config
            assert not set(loader.skrl_runner_config(cfg)) & set(loader.SKRL_PROJECT_KEYS)
            hooks = loader.skrl_callbacks(cfg, Path("elsewhere"))
            if algo == "ppo":
                (hook,) = hooks
                assert isinstance(hook, SkrlSelect) and hook.save_path == Path("elsewhere")
                assert (hook.every, hook.episodes) == (alg.STATE_ENV_STEPS[env_id.split("-")[0]] // 40, 30)
            else:
                assert hooks == []
    # the skrl SAC defaults row's file: skrl's SAC_CFG as it comes, no wrapper, only what the runner needs
    path = loader.skrl_path("sac-defaults", "GraspLift-IRB120-v1")
    cfg = loader.skrl_config("sac-defaults", "TableClearing-IRB120-v1")
    assert uncommented_keys(path) == [] and cfg["agent"] == {"class": "SAC"}
    assert loader.skrl_env_settings(cfg) == (4, []) and alg.ALGORITHMS["skrl-sac"].config == "sac-defaults"


def test_the_skrl_sac_configs_sample_a_squashed_gaussian(alg):
    """skrl's GaussianMixin samples an unsquashed Gaussian and, with ``clip_actions``, scores the clipped sample by
    the Gaussian's density. With a linear mean that bought SAC's entropy bonus without end as the mean left [-1, 1]
    (the probe ``skrl_sac_linear_mean``: Q ~ 1e8); with a tanh mean, as σ grew (``skrl_sac_clipped_sample``: σ at
    its clamp, 7.4). Each tuned file's policy is a ``SquashedGaussianMixin``, built as ``make_runner`` builds it
    (the next test runs one through skrl's Runner): its sample and mean stay within the bounds whatever the
    input, and its log-probability is the squashed density's, finite at the bounds."""
    pytest.importorskip("skrl")
    import gymnasium as gym
    import numpy as np
    import torch

    from agents.configs import loader
    from maniskill_irb120.integrations.skrl import TanhSquashed, squashed_gaussian_model

    torch.manual_seed(0)
    obs = torch.randn(256, 30) * 1e3  # far outside anything the scaler passes
    spaces = dict(observation_space=gym.spaces.Box(-np.inf, np.inf, (30,)), action_space=gym.spaces.Box(-1, 1, (5,)))
    for env_id in alg.TASKS.values():
        spec = dict(loader.skrl_config("sac", env_id)["models"]["policy"])
        assert spec.pop("class") == "SquashedGaussianMixin" and not spec.get("clip_actions"), env_id
        policy = squashed_gaussian_model(device="cpu", **spaces, **spec)
        assert isinstance(policy, TanhSquashed)
        actions, out = policy.act({"observations": obs}, role="policy")
        assert out["mean_actions"].abs().max() <= 1.0 and actions.abs().max() <= 1.0, env_id
        assert torch.isfinite(out["log_prob"]).all(), env_id


def test_a_skrl_sac_cell_resumes_with_its_replay_memory_and_temperature(alg, tmp_path, monkeypatch):
    """skrl's ``agent.save`` keeps the models, optimisers and scaler, not the replay memory or SAC's temperature,
    and skrl's trainer counts its timesteps from 0 in every session; a resumed skrl SAC cell used to go on from an
    empty memory, its random steps again and the initial temperature (the first skrl SAC screening cell read α 0.1
    throughout its second session). The cell keeps ``replay.pt`` beside ``agent.pt``; a rerun restores it, and the
    memory goes on from the rows the first session filled."""
    pytest.importorskip("skrl")
    import math
    from types import SimpleNamespace

    import torch
    import yaml

    from agents.configs import loader
    from maniskill_irb120.integrations import skrl as adapter

    for env_id in alg.TASKS.values():  # the tuned files' memory holds the budget's env steps, no more
        cfg = loader.skrl_config("sac", env_id)
        budget = alg.STATE_ENV_STEPS[env_id.split("-")[0]]
        assert cfg["memory"]["memory_size"] * loader.skrl_env_settings(cfg)[0] == budget
    cfg = loader.skrl_config("sac", "GraspLift-IRB120-v1")
    cfg["memory"] = dict(cfg["memory"], memory_size=64)  # a toy memory: the test's 24 rows fit
    cfg["agent"] = dict(cfg["agent"], random_timesteps=4, learning_starts=8)  # vector steps
    conf = tmp_path / "sac.yaml"
    conf.write_text(yaml.safe_dump(cfg))
    cell = "state/GraspLift/skrl-sac-tuned/s1"
    ckpt = tmp_path / "runs" / "state__GraspLift__skrl-sac-tuned__s1"

    def run(out: str, env_steps: int) -> None:
        alg.main(alg.Args(only=[cell], out_dir=tmp_path / out, runs_dir=tmp_path / "runs", quick=True,
                          conf_file=conf, total_env_steps=env_steps, eval_episodes=1, curve_points=1,
                          reference_steps=0))  # fmt: skip

    run("first", 64)
    first = torch.load(ckpt / "replay.pt", weights_only=False)
    assert first["rows"] == first["memory_index"] == 16 and not first["filled"]  # 64 env steps of 4 envs
    assert set(first["tensors"]) >= {"observations", "actions", "rewards", "next_observations"}
    log_alpha = float(first["log_entropy_coefficient"])
    assert not math.isclose(log_alpha, math.log(0.1), abs_tol=1e-6)  # 8 vector steps of updates moved it

    restored = {}
    real = adapter.restore_off_policy_state

    def restore(agent, state, done):
        real(agent, state, done)
        restored.update(squashed=isinstance(agent.policy, adapter.TanhSquashed),  # the YAML's, through skrl's Runner
                        done=done, rows=agent.memory.memory_index, random=agent.cfg.random_timesteps,
                        starts=agent.cfg.learning_starts, log_alpha=float(agent.log_entropy_coefficient.detach()),
                        obs=agent.memory.tensors["observations"][:16].clone())  # fmt: skip

    monkeypatch.setattr(adapter, "restore_off_policy_state", restore)
    run("second", 96)  # another table, the same cell's folder: it continues from 64 env steps
    assert restored["squashed"]
    assert restored["done"] == 16 and restored["rows"] == 16 and restored["random"] == restored["starts"] == 0
    assert restored["log_alpha"] == log_alpha
    assert torch.equal(restored["obs"], first["tensors"]["observations"])
    second = torch.load(ckpt / "replay.pt", weights_only=False)
    assert second["rows"] == 24  # the first session's 16 rows and 8 more, not 8 from an empty memory
    for name, tensor in first["tensors"].items():
        assert torch.equal(second["tensors"][name][:16], tensor), name
    # a memory of another shape (another config's) is refused by name, before anything is copied
    own = torch.zeros(64, 4, 30)
    agent = SimpleNamespace(memory=SimpleNamespace(tensors={"observations": own}), cfg=None)
    bad = dict(first, tensors={"observations": torch.ones(16, 4, 3)})
    with pytest.raises(ValueError, match=r"'observations' \(16, 4, 3\) does not fit this agent's memory \(64, 4, 30\)"):
        real(agent, bad, 16)
    assert not own.any()


def test_the_camera_config_is_the_state_ones_with_what_pixels_change(alg):
    """sb3/ppo_rgbd.yml: every setting says why and differs from SB3's default; it is sb3/ppo.yml's but for the
    policy class, the image left out of VecNormalize (which would make it floats SB3 then flattens into the MLP)
    and a sparser selection; an algorithm with no camera file is refused by name."""
    import inspect

    from agents.configs import loader

    path = loader.sb3_path("ppo", "rgbd")
    assert path.name == "ppo_rgbd.yml" and uncommented_keys(path) == []
    params = inspect.signature(loader.sb3_class("ppo").__init__).parameters
    for env_id in alg.TASKS.values():
        cam, state = loader.sb3_config("ppo", env_id, obs="rgbd"), loader.sb3_config("ppo", env_id)
        assert cam.policy == "MultiInputPolicy" and cam.n_timesteps == alg.CAMERA_ENV_STEPS
        assert cam.normalize == {"norm_obs": True, "norm_reward": False, "norm_obs_keys": ["state"]}
        assert cam.kwargs == state.kwargs and cam.n_envs == state.n_envs == 4
        assert all(key in params and params[key].default != value for key, value in cam.kwargs.items())
        assert [(w.func, w.keywords) for w in cam.wrappers] == [(w.func, w.keywords) for w in state.wrappers]
        (select,) = cam.make_callbacks(Path("elsewhere"))
        assert (select.every, select.episodes) == (alg.CAMERA_ENV_STEPS // 20, 30)
    with pytest.raises(ValueError, match="no camera config for SB3 sac"):
        loader.sb3_path("sac", "rgbd")
    with pytest.raises(ValueError, match="has no entry for Foo-v1; it has GraspLift-IRB120-v1"):
        loader.sb3_config("ppo", "Foo-v1", obs="rgbd")
    assert "sb3-ppo-tuned" in alg.CAMERA_ALGOS and "ppo_rgbd.yml" in alg.settings_of("rgbd", "sb3-ppo-tuned")
    assert alg.settings_of("state", "sb3-ppo-tuned") == alg.ALGORITHMS["sb3-ppo-tuned"].settings


@pytest.mark.parametrize(
    "argv, message",
    [
        (["-conf", "agents/configs/sb3/ppo_rgbd.yml"], "MultiInputPolicy and obs_mode state disagree"),
        (["--env-kwargs", "obs_mode"], "give KEY:VALUE, e.g. obs_mode:rgbd"),
        (["--env-kwargs", "obs_mode:pixels"], "obs_mode:pixels: unknown; use one of state, rgbd"),
        (["--env-kwargs", "obs_mode:rgbd", "--algo", "sac"], "no camera config for SB3 sac"),
        (["--env-kwargs", "obs_mode:rgbd", "--library", "skrl"], "the skrl configs are for state observations"),
        (["--env-kwargs", "reward_mode:a b"], "is neither a Python literal nor a word"),
    ],
)
def test_the_train_command_refuses_an_observation_its_config_does_not_read(argv, message, capsys):
    """One line and exit code 2 for each, before any env is built."""
    from agents.configs import train

    with pytest.raises(SystemExit) as e:
        train.parse(["--algo", "ppo", "--env", "GraspLift-IRB120-v1", *argv])
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_every_train_command_of_the_docs_parses(alg):
    """docs/rl_libraries.md's commands of agents.configs.train, as a user pastes them: each parses and its config
    agrees with its observation (the check parse makes before any env is built)."""
    import shlex

    from agents.configs import train

    doc = (alg.ROOT / "docs" / "rl_libraries.md").read_text()
    commands = [line for line in doc.splitlines() if line.startswith(".venv/bin/python -m agents.configs.train ")]
    assert len(commands) >= 4 and any("obs_mode:rgbd" in c for c in commands)
    for command in commands:
        argv = shlex.split(command.split("#")[0])[3:]
        assert train.parse(argv).algo, command


def test_the_train_command_reads_rl_zoo3s_env_kwargs():
    from agents.configs import train

    a = train.parse(["--algo", "ppo", "--env", "GraspLift-IRB120-v1", "--env-kwargs", "obs_mode:rgbd",
                     "reward_mode:'dense'", "sensor_noise:0.5"])  # fmt: skip
    assert a.env_kwargs == {"obs_mode": "rgbd", "reward_mode": "dense", "sensor_noise": 0.5}
    assert train.parse(["--algo", "ppo", "--env", "GraspLift-IRB120-v1"]).env_kwargs == {}


def test_the_camera_config_builds_a_cnn_policy_on_the_unnormalised_image():
    """The model the camera cell trains: NatureCNN on the image key, and VecNormalize touching the state only."""
    import numpy as np
    from stable_baselines3 import PPO
    from stable_baselines3.common.torch_layers import NatureCNN

    from agents.configs import loader

    cfg = loader.sb3_config("ppo", "GraspLift-IRB120-v1", obs="rgbd")
    venv = cfg.vec_env("GraspLift-IRB120-v1", num_envs=1, obs="rgbd", backend="cpu", seed=3)
    try:
        model = PPO(cfg.policy, venv, seed=3, **cfg.model_kwargs(5))
        obs = venv.reset()
        raw = venv.get_original_obs()
        assert obs["image"].dtype == np.uint8 and np.array_equal(obs["image"], raw["image"])
        assert not np.allclose(obs["state"], raw["state"])  # normalised
        assert isinstance(model.policy.features_extractor.extractors["image"], NatureCNN)
        action, _ = model.predict(obs, deterministic=True)
        assert action.shape == (1, 5) and np.isfinite(action).all()
    finally:
        venv.close()


def test_every_probe_config_loads_and_its_run_command_names_itself(alg):
    """A probe's config is read by the tuned cell it names (--conf-file): it must load as that library's config, carry
    only keys the library knows (skrl's runner would drop an unknown one; SB3's constructor refuses one, checked by
    building the keywords' names against its signature), and say in its header the command that ran it, with its
    own path and its own output folders."""
    import inspect

    pytest.importorskip("sb3_contrib")
    from skrl.agents.torch.ppo import PPO_CFG
    from skrl.agents.torch.sac import SAC_CFG

    from agents.configs import loader

    probes = sorted((alg.ROOT / "benchmarks" / "configs" / "probes").iterdir())
    assert probes
    for path in probes:
        head = " ".join(line.lstrip("# ").strip() for line in path.read_text().splitlines() if line.startswith("#"))
        rel = path.relative_to(alg.ROOT).as_posix()
        assert f"--conf-file {rel}" in head and f"benchmarks/results/probes/{path.stem}" in head, path.name
        assert f"runs/probes/{path.stem}" in head, path.name
        cell = head.split("--only ", 1)[1].split()[0]
        task, algo = cell.split("/")[1:3]
        assert algo in alg.TUNED_ALGOS and task in alg.TASKS, (path.name, cell)
        env_id = alg.TASKS[task]  # the task the probe's cell trains on: its config must carry that task's entry
        if path.suffix == ".yaml":  # skrl's runner YAML
            cfg = loader.skrl_config(algo, env_id, path)
            defaults = {"PPO": PPO_CFG(), "SAC": SAC_CFG()}[cfg["agent"]["class"]]
            for key in cfg["agent"]:
                if key != "class":
                    getattr(defaults, key)  # an AttributeError names a key skrl does not know
        else:  # rl-zoo3's hyperparams
            cfg = loader.sb3_config(algo.split("-")[1], env_id, path)
            params = inspect.signature(loader.sb3_class(cfg.algo).__init__).parameters
            assert set(cfg.kwargs) <= set(params), (path.name, set(cfg.kwargs) - set(params))


def test_absorbing_success_adds_the_absorbing_value_on_a_terminating_success_only():
    import gymnasium as gym
    import torch

    from maniskill_irb120.integrations.wrappers import AbsorbingSuccess

    class Fake(gym.Env):
        observation_space, action_space = gym.spaces.Box(-1, 1, (1,)), gym.spaces.Box(-1, 1, (1,))

        def step(self, action):
            info = {"success": torch.tensor([True, True, False])}
            return 0, torch.tensor([1.0, 0.5, 0.2]), torch.tensor([True, False, True]), torch.tensor([False] * 3), info

    _, reward, *_ = AbsorbingSuccess(Fake(), gamma=0.8).step(None)
    assert torch.allclose(reward, torch.tensor([1.0 + 0.8 / 0.2, 0.5, 0.2]))  # 1 + γ·1/(1−γ) = 1/(1−γ)
    with pytest.raises(ValueError):
        AbsorbingSuccess(Fake(), gamma=1.0)


def test_action_penalty_charges_the_arms_squared_action_not_the_gripper_and_refuses_a_bad_coef():
    import gymnasium as gym
    import torch

    from maniskill_irb120.integrations.wrappers import ActionPenalty

    class Fake(gym.Env):
        observation_space, action_space = gym.spaces.Box(-1, 1, (1,)), gym.spaces.Box(-1, 1, (5,))

        def step(self, action):
            return 0, torch.tensor([1.0, 0.5]), torch.tensor([False, True]), torch.tensor([False] * 2), {}

    env = ActionPenalty(Fake(), coef=0.1)
    action = torch.tensor([[1.0, -1.0, 0.0, 0.0, -1.0], [2.0, 0.0, 0.0, 0.0, 1.0]])  # 2.0: clipped as the controller
    _, reward, *_ = env.step(action)
    assert torch.allclose(reward, torch.tensor([1.0 - 0.1 * 2 / 4, 0.5 - 0.1 * 1 / 4]))
    with pytest.raises(ValueError, match="5 components"):
        env.step(torch.zeros(2, 4))
    _, reward, *_ = env.step(torch.zeros(2, 5))  # still usable after the refused call
    assert torch.equal(reward, torch.tensor([1.0, 0.5]))
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="coef"):
            ActionPenalty(Fake(), coef=bad)


@pytest.mark.slow  # four cells' worker start-ups, ten held-out points each and evaluations (2-4 min on 2 cores)
def test_tuned_cells_run_from_their_configs_and_log_a_held_out_curve(alg, tmp_path, capsys):
    pytest.importorskip("sb3_contrib")
    pytest.importorskip("skrl")
    cells = [
        "state/GraspLift/sb3-ppo-tuned/s1",
        "state/GraspLift/sb3-tqc-tuned/s1",
        "state/GraspLift/skrl-sac-tuned/s1",
        "state/GraspLift/skrl-sac/s1",
    ]
    args = alg.Args(only=cells, out_dir=tmp_path, runs_dir=tmp_path / "runs", quick=True, total_env_steps=400,
                    reference_steps=0, progress_s=1e-6)  # fmt: skip
    alg.main(args)
    out = capsys.readouterr().out
    data = json.loads((tmp_path / "algorithms.json").read_text())
    for cell in cells:  # each cell shows its env steps of the budget, their rate and the time left as it trains
        assert re.search(rf"\[algorithms {re.escape(cell)}\] [\d,]+/400 env steps \(\d+ %\) \| [\d.]+ env steps/s \| "
                         r"\S+ elapsed, ETA \S+", out), out[-2000:]  # fmt: skip
        one = data["cells"][cell]
        curve = one["held_out_curve"]
        assert one["env_steps"] >= 400 and len(curve["env_steps"]) == 11  # tenths, a quarter, the final evaluation
        assert curve["env_steps"] == sorted(curve["env_steps"]) and curve["episodes"][:-1] == [1] * 10
        assert curve["episodes"][-1] == len(one["successes"]) and curve["eval_s"][-1] is None
        assert all(lo <= s <= hi for (lo, hi), s in zip(curve["ci95"], curve["success"]))
    rows = {r["algorithm"]: r for r in data["rows"] if r["task"] == "GraspLift" and r["obs"] == "state"}
    assert all(v is not None for v in rows["sb3-ppo-tuned"]["held_out_at"].values())
    model = tmp_path / "runs" / "state__GraspLift__sb3-ppo-tuned__s1"
    assert (model / "vecnormalize.pkl").is_file()  # the config's normalize reached the cell


@pytest.mark.slow  # one SB3 and one skrl run of a few hundred env steps (~40-80 s on 2 cores)
def test_the_train_command_runs_a_config_as_rl_zoo3_and_isaac_lab_would(tmp_path):
    pytest.importorskip("skrl")
    from agents.configs import train

    out = train.main(["--algo", "ppo", "--env", "GraspLift-IRB120-v1", "-conf", "agents/configs/sb3/ppo.yml",
                      "-n", "600", "-f", str(tmp_path), "--gym-packages", "maniskill_irb120"])  # fmt: skip
    assert (out / "GraspLift-IRB120-v1.zip").is_file() and (out / "vecnormalize.pkl").is_file()
    out = train.main(["--library", "skrl", "--algo", "ppo", "--env", "GraspLift-IRB120-v1", "-n", "600", "-f",
                      str(tmp_path)])  # fmt: skip
    assert out.is_dir()


def test_the_held_out_curve_is_read_at_a_quarter_a_half_and_the_end_of_the_budget(alg):
    from agents.common.evaluation import curve_fractions

    assert curve_fractions(10) == [0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9] and curve_fractions(1) == []
    clock = alg.Budget(None, 0.0, 60.0, total_steps=1000)
    held: list = []
    due = []
    for steps in range(0, 1001, 50):
        if clock.eval_due(held, steps, 10):
            held.append([steps])
            due.append(steps)
    assert due == [100, 200, 250, 300, 400, 500, 600, 700, 800, 900]  # the end is the final evaluation's
    curve = {"env_steps": [*due, 1000], "success": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]}
    runs = [{"held_out_curve": curve, "total_env_steps": 1000}, {"held_out_curve": curve, "total_env_steps": 1000}]
    assert alg.held_out_at(runs) == {"0.25": 0.2, "0.5": 0.5, "1": 1.0}
    assert alg.held_out_at([*runs, {"total_env_steps": 1000}]) == {"0.25": None, "0.5": None, "1": None}


def test_the_curves_are_the_iqm_over_seeds_at_each_share_with_a_two_level_interval(alg):
    """Three seeds' held-out curves: the IQM of 3 values trims none (as scipy's trim_mean, rliable's IQM), a point
    all seeds share is kept, and the interval holds the IQM and widens with fewer episodes a point."""
    import numpy as np

    from benchmarks.lib.stats import iqm_ci

    def cell(seed, success, total=1000):
        steps = [100, 250, 500, total][: len(success)]
        episodes = [30] * (len(success) - 1) + [100]
        curve = {"env_steps": steps, "success": success, "episodes": episodes}
        return {"cell": f"state/GraspLift/sb3-sac-tuned/s{seed}", "seed": seed, "total_env_steps": total,
                "held_out_curve": curve}  # fmt: skip

    cells = {
        c["cell"]: c
        for c in (cell(1, [0.0, 0.2, 0.9, 1.0]), cell(2, [0.0, 0.4, 0.5, 0.9]), cell(3, [0.1, 0.3, 0.7, 0.8]))
    }
    cells["state/GraspLift/sb3-sac-tuned/s4"] = cell(4, [0.0, 1.0], total=2000)  # another budget: left out
    (curve,) = alg.curves_of(cells, 2000)
    assert curve["algorithm"] == "sb3-sac-tuned" and curve["seeds"] == [1, 2, 3]
    assert curve["env_steps"] == [100, 250, 500, 1000]
    assert curve["iqm"] == pytest.approx([0.1 / 3, 0.3, 0.7, 0.9])  # 3 seeds: floor(0.75) = 0 trimmed each side
    assert all(lo <= m <= hi for m, (lo, hi) in zip(curve["iqm"], curve["ci95"]))
    rng = np.random.default_rng(0)
    wide, narrow = iqm_ci([0.5, 0.5], [10, 10], 4000, rng), iqm_ci([0.5, 0.5], [1000, 1000], 4000, rng)
    assert narrow[2] - narrow[1] < (wide[2] - wide[1]) / 4
    with pytest.raises(ValueError, match="rates"):
        iqm_ci([1.5], [10], 10, rng)


def test_two_runs_of_one_out_dir_keep_each_others_cells(alg, tmp_path):
    """Two lanes of cells side by side write one algorithms.json: each report keeps the cells the other wrote
    since it started, a lane's own cell wins over the file's copy, and the other lane's cell is the file's newest
    (its reference speed, added after the cell, is not lost to a copy read before)."""
    args = alg.Args(out_dir=tmp_path, runs_dir=tmp_path / "runs", results_md=results_md(tmp_path), bootstrap=50)

    def cell(algo, rate):
        return {"cell": f"state/GraspLift/{algo}/s1", "seed": 1, "success_rate": rate, "successes": [int(rate)] * 4,
                "env_steps": 100, "wall_clock_s": 1.0, "budget_min": 1.0, "date": "2026-12-05 05:00 UTC"}  # fmt: skip

    sac, tqc = "state/GraspLift/sb3-sac-tuned/s1", "state/GraspLift/sb3-tqc-tuned/s1"
    lane_a, lane_b = {sac: cell("sb3-sac-tuned", 1.0)}, {tqc: cell("sb3-tqc-tuned", 0.0)}
    alg.write_report(lane_a, args, frozenset({sac}))
    alg.write_report(lane_b, args, frozenset({tqc}))  # started before lane a's cell was written: reads it now
    lane_a[sac] = cell("sb3-sac-tuned", 0.0)  # the same cell again, rerun
    alg.write_report(lane_a, args, frozenset({sac}))
    cells = json.loads((tmp_path / "algorithms.json").read_text())["cells"]
    assert sorted(cells) == [sac, tqc] and cells[sac]["success_rate"] == 0.0
    lane_a[sac]["reference_sps"] = [300.0, 290.0]  # lane a times the machine after its cell
    alg.write_report(lane_a, args, frozenset({sac}))
    lane_b[tqc]["reference_sps"] = [280.0, 270.0]  # lane b, holding lane a's cell from before, does the same
    alg.write_report(lane_b, args, frozenset({tqc}))
    cells = json.loads((tmp_path / "algorithms.json").read_text())["cells"]
    assert cells[sac]["reference_sps"] == [300.0, 290.0] and cells[tqc]["reference_sps"] == [280.0, 270.0]


def test_a_skrl_configs_selection_hook_keeps_the_best_on_validation_and_the_cell_deploys_it(alg, tmp_path, monkeypatch):
    """A ``callback:`` entry of the project's skrl YAML (integrations.skrl.SelectOnValidation) reaches the skrl cell:
    after the agent's own post_interaction it checks the deterministic policy on validation seeds every ``every``
    env steps, saves the best agent in the cell's folder, and the cell's held-out score is the saved agent's (it acts
    exactly as the policy did when it was checked), the last policy's kept beside it.

    The same trained cell then takes --validate (one skrl cell trained for both, as the SB3 test below does): it
    rebuilds the agent from its config, loads what training saved last (the models and the observation scaler) and
    plays it on VALIDATION_SEED onwards, acting as the last policy did on the held-out seeds; and
    scripts/diagnose_policy.py plays the same saved agent through the same loader, its critic beside it."""
    pytest.importorskip("skrl")
    import gymnasium as gym
    import torch
    import yaml

    import maniskill_irb120  # noqa: F401
    from agents.configs import loader
    from maniskill_irb120.integrations import selection

    env = gym.make("GraspLift-IRB120-v1", obs_mode="state", render_backend="none")
    try:
        probe, _ = env.reset(seed=3)
    finally:
        env.close()
    flat = {"state": probe}
    acted = {}  # each check's action on one fixed observation, as the policy was when checked
    real_check = selection.held_out_success

    def check(act, env_id, obs, episodes, *, seed):
        acted[len(acted)] = torch.as_tensor(act(probe[0].numpy()))
        return real_check(act, env_id, obs, episodes, seed=seed)

    monkeypatch.setattr(selection, "held_out_success", check)
    final = []  # each evaluation's act, its seeds and its action on the probe when it was called
    real = alg.evaluate_on_seeds
    monkeypatch.setattr(alg, "evaluate_on_seeds", lambda act, env_id, obs, seeds: final.append(
        (act, seeds, act(flat))) or real(act, env_id, obs, seeds))  # fmt: skip
    cfg = loader.skrl_config("ppo", "GraspLift-IRB120-v1")
    cfg["callback"] = [{"maniskill_irb120.integrations.skrl.SelectOnValidation": {"every": 128, "episodes": 1}}]
    conf = tmp_path / "ppo_select.yaml"
    conf.write_text(yaml.safe_dump(cfg))
    cell = "state/GraspLift/skrl-ppo-tuned/s1"
    args = alg.Args(only=[cell], out_dir=tmp_path / "out", runs_dir=tmp_path / "runs", quick=True, conf_file=conf,
                    total_env_steps=520, eval_episodes=1, curve_points=1, reference_steps=0)  # fmt: skip
    one = alg.main(args)["cells"][cell]
    best = tmp_path / "runs" / "state__GraspLift__skrl-ppo-tuned__s1" / "best"
    kept = json.loads((best / "best.json").read_text())
    # 4 envs: 128 vector steps fill the rollout, whose update (at 512) comes before that step's check
    assert [c[0] for c in kept["checks"]] == [128, 256, 384, 512] and (best / "best_agent.pt").is_file()
    top = max(c[1] for c in kept["checks"])
    first_top = next(i for i, c in enumerate(kept["checks"]) if c[1] == top)
    assert one["selected"]["env_steps"] == kept["checks"][first_top][0] and one["selected"]["checks"] == kept["checks"]
    assert one["selected"]["first_seed"] == alg.VALIDATION_SEED
    assert len(one["last_policy_successes"]) == len(one["successes"])
    assert not torch.equal(acted[0], acted[3])  # the update moved the policy, so the two candidates differ
    last_policy = final[-2][2]  # the cell scores the last policy, then the selected one
    assert final[-2][1][0] == alg.EVAL_SEED and torch.equal(final[-1][2][0], acted[first_top])
    assert torch.equal(final[-1][0](flat)[0], acted[first_top])  # the cell deploys the selected agent, as it was
    rerun_finished_cell(alg, args, cell, one)  # trains nothing and deploys the same kept agent
    assert torch.equal(final[-1][0](flat)[0], acted[first_top])
    # --validate: the saved last agent on the validation seeds
    report = alg.main(alg.Args(only=[cell], out_dir=tmp_path / "out", runs_dir=tmp_path / "runs", validate=True,
                               eval_episodes=1))  # fmt: skip
    v = report["cells"][cell]["validation"]
    assert (v["episodes"], v["first_seed"], v["env_steps"]) == (1, alg.VALIDATION_SEED, one["env_steps"])
    validate_act, seeds, _ = final[-1]
    assert seeds == [alg.VALIDATION_SEED] and torch.equal(validate_act(flat), last_policy)  # its scaler and weights
    # scripts/diagnose_policy.py plays the same saved agent through the same loader, its critic beside it
    spec = importlib.util.spec_from_file_location(
        "diagnose_policy", Path(__file__).parents[2] / "scripts" / "diagnose_policy.py"
    )
    diagnose = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = diagnose  # its dataclass looks its module up
    spec.loader.exec_module(diagnose)
    agent_pt = tmp_path / "runs" / cell.replace("/", "__") / "agent.pt"
    model = diagnose.SkrlModel(cell, agent_pt)
    assert torch.equal(torch.as_tensor(model.predict(probe.numpy())[0]), last_policy)
    assert model.gamma == 0.8 and model.num_timesteps == one["env_steps"]  # the YAML's discount_factor
    assert math.isfinite(model.value(probe.float())[0])
    from maniskill_irb120.integrations.skrl import deterministic_value

    batch = deterministic_value(model.agent, model.space, torch.stack([probe, probe + 0.05]))  # one value per row
    assert batch.shape == (2,) and batch[0] != batch[1]
    assert float(batch[0]) == pytest.approx(model.value(probe)[0], rel=1e-5)
    out = tmp_path / "diagnosis.json"
    diagnose.cli(["--model", str(agent_pt), "--skrl-cell", cell, "--episodes", "1", "--max-steps", "3",
                  "--out", str(out)])  # fmt: skip
    r = json.loads(out.read_text())
    assert r["algo"] == f"skrl {cell}" and r["episode_len"] == 3 and r["stages"][0]["steps"] == 3
    with pytest.raises(SystemExit) as e:  # an SB3 cell is refused by name
        diagnose.cli(["--model", str(agent_pt), "--skrl-cell", "state/GraspLift/sb3-ppo-tuned/s1"])
    assert e.value.code == 2


def rerun_finished_cell(alg, args, cell: str, one: dict) -> dict:
    """``cell`` run again after its training was over but before its result was written (its entry taken out of
    ``args.out_dir``'s report): it trains nothing more and reports the checkpoint its selection kept."""
    report_path = args.out_dir / "algorithms.json"
    report = json.loads(report_path.read_text())
    del report["cells"][cell]
    report_path.write_text(json.dumps(report))
    again = alg.main(args)["cells"][cell]
    assert again["selected"]["env_steps"] == one["selected"]["env_steps"] and again["env_steps"] == one["env_steps"]
    return again


def test_a_configs_selection_callback_keeps_the_best_on_validation_and_the_cell_scores_it(
    alg, tmp_path, capsys, monkeypatch
):
    """An rl-zoo3 ``callback:`` entry (SelectOnValidation) reaches the cell: it checks the policy on validation seeds
    while training, keeps the best in the cell's folder, and the cell's held-out score is the selected policy's, the
    last policy's kept beside it; the loader builds the same callback for agents.configs.train.

    The same trained cell then takes --validate (one SB3 cell trained for both: training one takes a minute on 2
    cores): it trains nothing, loads the cell's saved model and observation statistics and plays them on
    VALIDATION_SEED onwards, so a choice between probes reads no held-out episode."""
    import yaml
    from stable_baselines3.common.vec_env import VecNormalize

    from agents.configs import loader
    from maniskill_irb120.integrations import sb3
    from maniskill_irb120.integrations.sb3 import SelectOnValidation

    norms = []  # every deterministic action of the cell's own evaluations: the selected policy's included, it is
    real_act = sb3.deterministic_action  # loaded without its envs and must act on the statistics saved beside it
    monkeypatch.setattr(sb3, "deterministic_action", lambda m, o, norm=None: norms.append(
        norm if norm is not None else m.get_vec_normalize_env()) or real_act(m, o, norm))  # fmt: skip
    hp = yaml.safe_load(loader.sb3_path("ppo").read_text())
    hp["GraspLift-IRB120-v1"]["callback"] = [
        {"maniskill_irb120.integrations.sb3.SelectOnValidation": {"every": 128, "episodes": 1}}
    ]
    hp["GraspLift-IRB120-v1"]["n_steps"] = 32  # rollouts of 4 x 32 env steps: two of them train in a quarter of 4 x 128
    conf = tmp_path / "ppo_select.yml"
    conf.write_text(yaml.safe_dump(hp))
    (made,) = loader.sb3_config("ppo", "GraspLift-IRB120-v1", conf).make_callbacks(tmp_path / "elsewhere")
    assert isinstance(made, SelectOnValidation) and made.save_path == tmp_path / "elsewhere" and made.every == 128
    cell = "state/GraspLift/sb3-ppo-tuned/s1"
    args = alg.Args(only=[cell], out_dir=tmp_path / "out", runs_dir=tmp_path / "runs", quick=True, conf_file=conf,
                    total_env_steps=150, reference_steps=0)  # fmt: skip
    first = alg.main(args)
    one = first["cells"][cell]
    best = tmp_path / "runs" / "state__GraspLift__sb3-ppo-tuned__s1" / "best"
    assert (best / "best_model.zip").is_file() and (best / "vecnormalize.pkl").is_file()
    kept = json.loads((best / "best.json").read_text())
    assert [c[0] for c in kept["checks"]] == [128, 256]  # 2 rollouts of 4 envs x 32 steps
    assert one["selected"]["env_steps"] in (128, 256) and one["selected"]["success"] == max(
        c[1] for c in kept["checks"]
    )
    assert one["selected"]["first_seed"] == alg.VALIDATION_SEED and one["selected"]["checks"] == kept["checks"]
    assert norms and all(isinstance(n, VecNormalize) for n in norms)  # the config normalises observations
    assert one["stopped_s"] == 0.0  # nothing stopped the process
    # a cell budgeted in env steps records its budget, no guard, and that nothing stopped it early
    assert one["total_env_steps"] == 150 and one["stopped_early"] is False
    assert one["max_minutes"] is None and "budget_min" not in one
    pending = next(r for r in first["rows"] if r["algorithm"] == "sb3-td3" and r["task"] == "TableClearing")
    assert pending["total_env_steps"] == 150 and "(150 env steps budget)" in alg.markdown(first["rows"])
    assert "last_policy_success" in one and len(one["last_policy_successes"]) == len(one["successes"])
    assert "validation success" in capsys.readouterr().out
    # a cell whose training was over when its run stopped (before its final evaluation) still deploys the selected one
    rerun_finished_cell(alg, args, cell, one)
    report_path = tmp_path / "out" / "algorithms.json"
    with pytest.raises(ValueError, match="positive"):
        SelectOnValidation(every=0)
    # --validate
    seen = []
    real = alg.evaluate_on_seeds
    monkeypatch.setattr(
        alg, "evaluate_on_seeds", lambda act, env_id, obs, seeds: seen.append(seeds) or real(act, env_id, obs, seeds)
    )
    report = alg.main(
        alg.Args(only=[cell], out_dir=tmp_path / "out", runs_dir=tmp_path / "runs", validate=True, eval_episodes=2)
    )
    v = report["cells"][cell]["validation"]
    assert seen == [[alg.VALIDATION_SEED, alg.VALIDATION_SEED + 1]] and alg.VALIDATION_SEED != alg.EVAL_SEED
    assert v["episodes"] == 2 and v["env_steps"] >= 150 and 0.0 <= v["success_rate"] <= 1.0
    assert json.loads(report_path.read_text())["cells"][cell]["validation"] == v
    with pytest.raises(ValueError, match="no saved model"):
        alg.main(alg.Args(only=[cell], out_dir=tmp_path / "out", runs_dir=tmp_path / "elsewhere", validate=True))


def test_the_docs_selection_callback_entry_builds_the_callback():
    """docs/rl_libraries.md's ``callback:`` example is what the loader reads into a SelectOnValidation."""
    import re

    import yaml

    from agents.configs import loader
    from maniskill_irb120.integrations.sb3 import SelectOnValidation

    doc = (Path(__file__).resolve().parents[2] / "docs" / "rl_libraries.md").read_text()
    (block,) = re.findall(r"```yaml\n(GraspLift-IRB120-v1:\n  callback:.*?)```", doc, re.S)
    (make,) = loader.wrappers_of(yaml.safe_load(block)["GraspLift-IRB120-v1"]["callback"])
    made = make()
    assert isinstance(made, SelectOnValidation) and (made.every, made.episodes) == (12500, 30)


def test_an_only_that_names_a_best_seed_not_yet_due_is_refused_before_any_cell(alg, tmp_path):
    """--only .../s3 on a table whose group has no seed-1 cells: s3 is a best seed, due only for the group's best,
    so the run would train nothing and end with exit status 0; it is refused with the flag that runs it now."""
    cell = "state/GraspLift/skrl-ppo-tuned/s3"
    with pytest.raises(ValueError, match=r"names state/GraspLift/skrl-ppo-tuned/s3, .* add --seeds 3 to run it now"):
        alg.main(alg.Args(only=[cell], out_dir=tmp_path, runs_dir=tmp_path / "runs"))
    assert not (tmp_path / "algorithms.json").exists() and not (tmp_path / "runs").exists()
    with_seeds = alg.Args(only=[cell], seeds=[3], out_dir=tmp_path)
    assert alg.waiting_cells({}, with_seeds) == [] and alg.planned({}, with_seeds) == [cell]
    # a glob over the group: its seed-1 cells run, so the others' best seeds waiting is no error
    group = alg.Args(only=["state/GraspLift/*"], out_dir=tmp_path)
    assert alg.waiting_cells({}, group) == [] and "state/GraspLift/skrl-ppo-tuned/s1" in alg.planned({}, group)
    # the cell done already: nothing planned, nothing refused
    assert alg.waiting_cells({cell: {}}, alg.Args(only=[cell], out_dir=tmp_path)) == []
