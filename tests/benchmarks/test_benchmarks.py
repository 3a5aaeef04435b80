"""Benchmarks run and write well-formed JSON (smoke only: timings are never asserted in tests)."""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.recipes import RECIPES
from agents.recipes import recipe as recipe_on
from benchmarks.lib import adopt, runner

REPO = Path(__file__).resolve().parents[2]
IN_GIT = (REPO / ".git").exists()  # a source checkout: --baseline can name its commits


@pytest.mark.slow
def test_sim_speed_quick_writes_json(tmp_path, bench_script):
    out = tmp_path / "sim_speed.json"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks.sim_speed",
            "--quick",
            "--json",
            str(out),
            "--plot",
            str(tmp_path / "p.png"),
            *(["--baseline", "HEAD"] if IN_GIT else []),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    if IN_GIT:  # the last commit's code measured beside this checkout's, in the same round
        assert set(r["ratios"]["vs_baseline"]) == {"render", "no_render"}
        assert all(v > 0 for v in r["ratios"]["vs_baseline"].values())
        assert len(r["baseline"]["commit"]) == 40 and r["baseline"]["ours"]["no_render"]["steps_per_s"] > 0
    section = bench_script("sim_speed").results_section(r, out, tmp_path / "p.png")
    assert section.startswith("## Simulator speed — `benchmarks/sim_speed.py`")
    assert "--quick" in section and "| state vs the original report's PyBullet loop without a camera |" in section
    assert ("Against the baseline commit" in section) == IN_GIT and "| this | no_render |" in section
    for mode in ("render_realtime", "render", "no_render"):
        assert r["env_steps_per_s"][mode] > 0
        assert r["reference_steps_per_s"]["pybullet_original"][mode] > 0
        assert set(r["ours"][mode]) >= {"mean", "std", "min", "p25", "p50", "p75", "max", "split_s", "peak_rss_mb"}
    assert r["reference_steps_per_s"]["pickcube_rgbd_84"] > 0
    assert r["floor"]["steps_per_s"] > 0 and 0 < r["ratios"]["rgbd_fraction_of_floor"] < 1.5
    for mode, suffix in (("rgbd", ""), ("state", "_state")):
        assert set(r["cpu_scaling"][mode]) == {"one", "one_worker", "two", "two_workers"}
        assert all(c["env_steps_per_s"] > 0 for c in r["cpu_scaling"][mode].values())
        for key in ("two_envs_vs_one", "two_workers_vs_one", "env_zero_here_vs_all_in_workers"):
            assert r["ratios"][key + suffix] > 0
    assert "## Action time" in run.stdout and (tmp_path / "p.png").stat().st_size > 1000


@pytest.mark.slow
def test_learning_quick_writes_json(tmp_path):
    """The recipe runner end to end at toy sizes: trainers as subprocesses, references, intervals, plot."""
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.learning", "--quick", "--out-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads((tmp_path / "learning.json").read_text())
    rows = {row["recipe"]: row for row in r["rows"]}
    assert set(rows) == {"random", "expert", "dagger-state", "ppo-state", "ppo-finetune-state", "sac-scratch-state"}
    for row in rows.values():
        lo, hi = row["success_ci95"]
        assert 0.0 <= lo <= row["success_mean"] <= hi <= 1.0
        assert all(len(one["successes"]) == 2 for one in row["runs"])
    assert rows["expert"]["success_mean"] == 1.0  # the scripted expert on the held-out seeds
    for name in ("dagger-state", "ppo-state", "ppo-finetune-state"):
        one = rows[name]["runs"][0]
        assert one["env_steps"] > 0 and one["wall_clock_s"] > 0 and Path(one["checkpoint"]).is_file()
    # ppo-state deploys the checkpoint it selected on validation seeds, and the row says which
    selected = rows["ppo-state"]["runs"][0]["selected"]
    assert selected["validation_episodes"] == 1 and rows["ppo-state"]["runs"][0]["checkpoint"].endswith("best.pt")
    # the fine-tuning starts from its own DAgger run, and the row counts both stages
    tuned, base = rows["ppo-finetune-state"]["runs"][0], rows["ppo-finetune-state"]["runs"][0]["base"]
    assert f"--base-checkpoint {base['checkpoint']}" in tuned["command"] and "__base" in base["checkpoint"]
    # (>=: a budget stop may leave a toy second stage no whole iteration on a slow machine)
    assert tuned["env_steps"] >= base["env_steps"] and tuned["wall_clock_s"] > base["wall_clock_s"]
    assert torch.load(tuned["checkpoint"], weights_only=False)["args"]["base_checkpoint"] == base["checkpoint"]
    assert "| dagger-state | state | 1 |" in run.stdout and (tmp_path / "learning.png").stat().st_size > 1000
    # each run trained here has the machine's speed on the reference workload just before and after it
    trained = [row for name, row in rows.items() if name not in ("random", "expert")]
    assert all(min(row["runs"][0]["reference_sps"]) > 0 for row in trained)
    assert "(reference env steps/s before / after: " in run.stdout


# a benchmark's smoke run (~20-40 s), as the other benchmarks' are; test_ppo.py's bf16 and fp32 update tests cover
# the updates it times, test_cli_errors.py its bad flag and test_results_sections.py its report
@pytest.mark.slow
def test_learner_speed_quick_times_every_configuration(tmp_path):
    """The camera update benchmark at toy sizes: the reference shift, fp32 and (where native) bf16 all timed on
    recorded expert frames."""
    from agents.common.precision import native_bf16

    out = tmp_path / "l.json"
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.learner_speed", "--quick", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    want = {"fp32, pad+crop shift", "fp32"} | ({"bf16 encoder"} if native_bf16(torch.device("cpu")) else set())
    assert {row["config"] for row in r["rows"]} == want
    assert all(row["ms"] > 0 and len(row["rounds_ms"]) == 1 for row in r["rows"]) and r["dataset"] > 20
    assert "| fp32 |" in run.stdout


@pytest.mark.slow  # a benchmark's smoke run (~1 min); RLlib's training path is tested in tests/agents/test_rllib.py
def test_rllib_speed_quick_writes_json(tmp_path):
    """RLlib against agents.ppo at toy sizes: both trainers measured, per-step timers and RSS read back."""
    pytest.importorskip("ray", reason="needs the ray extra")
    out = tmp_path / "r.json"
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.rllib_speed", "--quick", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    assert {(row["trainer"], row["runners"]) for row in r["rows"]} == {
        ("agents.ppo", 1),
        ("rllib PPO", 0),
        ("rllib PPO", 1),
    }
    for row in r["rows"]:
        assert row["sampled"] > 0 and row["trained"] > 0 and row["startup_s"] > 0
    remote = [row for row in r["rows"] if row["runners"] == 1 and row["trainer"] == "rllib PPO"][0]
    assert remote["rss_mb_per_runner"] > 100 and remote["per_step_ms"]["env_step"] > 0
    assert r["versions"]["ray"] == "2.60.0" and "| rllib PPO | 1 | 1 |" in run.stdout


def test_sim2real_gap_runs_the_named_rows(tmp_path, bench_script):
    out = tmp_path / "gap.json"
    cmd = [sys.executable, "-m", "benchmarks.sim2real_gap", "--episodes", "1", "--out", str(tmp_path)]
    run = subprocess.run(
        [*cmd, "--shifts", "lighting", "none", "--workers", "2", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    # two cells, each in its own process with its own emulator, reported in the table's order
    assert [row["shift"] for row in r["rows"]] == ["none", "lighting"] and r["workers"] == 2 and r["sim_shift"]
    assert "the sim side: in each row's condition" in run.stdout
    assert all(row["real_success"] in (0.0, 1.0) and row["late_steps"] == 0 for row in r["rows"])
    assert all(row["sim_collision"] in (0.0, 1.0) for row in r["rows"])  # both sides' collisions are kept
    # each cell's paired count: its one seed is discordant exactly when the two sides disagree
    for row in r["rows"]:
        p = row["paired"]
        assert p["episodes"] == 1 and (p["sim_only"], p["real_only"]) == (
            int(row["sim_success"] > row["real_success"]),
            int(row["real_success"] > row["sim_success"]),
        )
    assert "McNemar p" in run.stdout
    assert "| expert | none |" in run.stdout and "| expert | lighting |" in run.stdout
    gap = bench_script("sim2real_gap")  # the refusals come before any work: checked in this process

    class WouldRun(Exception):
        pass

    def would_run(cfg):
        raise WouldRun(cfg.out.name)

    gap.evaluate = would_run  # --reuse reads the finished cells above instead of running them again
    again = gap.main(gap.Args(shifts=["lighting", "none"], episodes=1, out=tmp_path, reuse=True))
    keys = ("shift", "spec", "sim_success", "real_success", "refused")
    assert [{k: row[k] for k in keys} for row in again["rows"]] == [{k: row[k] for k in keys} for row in r["rows"]]
    with pytest.raises(WouldRun, match="none"):  # another configuration (episodes) is run, not read
        gap.main(gap.Args(shifts=["none"], episodes=2, out=tmp_path, reuse=True))
    with pytest.raises(WouldRun, match="none"):  # and without --reuse nothing is read
        gap.main(gap.Args(shifts=["none"], episodes=1, out=tmp_path))
    with pytest.raises(WouldRun, match="lighting"):  # rows run in the order named, though reported in the table's
        gap.main(gap.Args(shifts=["lighting", "none"], episodes=1, out=tmp_path, workers=1))
    # the rows --json holds are read where the cells' folders are gone (another machine): a committed table takes
    # more rows without running its old ones again
    table = out.read_text()
    elsewhere = tmp_path / "elsewhere"
    from_json = gap.main(gap.Args(shifts=["none", "lighting"], episodes=1, out=elsewhere, reuse=True, json=out))
    assert [{k: row[k] for k in keys} for row in from_json["rows"]] == [{k: row[k] for k in keys} for row in r["rows"]]
    assert not elsewhere.exists() and all(row["run"]["config"] for row in json.loads(out.read_text())["rows"])
    with pytest.raises(WouldRun, match="none"):  # another configuration is run
        gap.main(gap.Args(shifts=["none"], episodes=2, out=elsewhere, reuse=True, json=out))
    with pytest.raises(WouldRun, match="none"):  # and a row is read only with --reuse
        gap.main(gap.Args(shifts=["none"], episodes=1, out=elsewhere, json=out))
    for spoil in (lambda row: row.pop("run"), lambda row: row["run"].update(error="RuntimeError: twin")):
        rows = json.loads(table)
        for row in rows["rows"]:
            spoil(row)  # a row from before rows kept their run, or one whose evaluation failed: run again
        out.write_text(json.dumps(rows))
        with pytest.raises(WouldRun, match="none"):
            gap.main(gap.Args(shifts=["none"], episodes=1, out=elsewhere, reuse=True, json=out))
    out.write_text(table)
    import torch

    def save_policy(path, w: float, **meta) -> None:  # a policy section, as a trainer or export-policy writes one
        section = dict(kind="dagger", env_id=gap.EvalConfig.env_id, state_dict={"w": torch.full((3,), w)})
        torch.save(dict(policy=section, **meta), path)

    policy, moved = tmp_path / "policy.pt", tmp_path / "moved" / "none"  # a checkpoint's cell, its folder moved
    save_policy(policy, 1.0)
    moved.mkdir(parents=True)
    report = json.loads((tmp_path / "none" / "report.json").read_text())
    assert report["policy_sha256"] is None  # the expert is no file
    report["config"]["policy"] = str(policy)
    report["policy_sha256"] = gap.policy_sha256(str(policy))
    (moved / "report.json").write_text(json.dumps(report))

    def args(p):
        return gap.Args(policy=(str(p),), shifts=["none"], episodes=1, out=tmp_path / "moved", reuse=True)

    read = gap.main(args(policy))
    assert read["rows"][0]["real_success"] == r["rows"][0]["real_success"]
    exported = tmp_path / "exported.pt"  # the same policy exported to another file, newer than the report: read
    save_policy(exported, 1.0, command="python -m agents.dagger ...", source=str(policy))
    assert hashlib.sha256(exported.read_bytes()).digest() != hashlib.sha256(policy.read_bytes()).digest()
    assert gap.main(args(exported))["rows"][0]["policy"] == str(exported)
    stale = {k: v for k, v in report.items() if k != "sim_side"}  # from before the sim side's condition was kept
    (moved / "report.json").write_text(json.dumps(stale))
    with pytest.raises(WouldRun, match="none"):
        gap.main(args(policy))
    (moved / "report.json").write_text(json.dumps(report))
    save_policy(policy, 2.0)  # other weights at the same path, older than the report: run again
    os.utime(policy, (time.time() - 60, time.time() - 60))
    with pytest.raises(WouldRun, match="none"):
        gap.main(args(policy))
    older = {k: v for k, v in report.items() if k != "policy_sha256"}  # a report from before the hash was kept:
    (moved / "report.json").write_text(json.dumps(older))  # read while the policy file at its path is older than it
    assert gap.main(args(policy))["rows"][0]["real_success"] == r["rows"][0]["real_success"]
    with pytest.raises(WouldRun, match="none"):  # but not for another path
        gap.main(args(exported))
    save_policy(policy, 3.0)  # and run again once the file is newer
    os.utime(policy, (time.time() + 60, time.time() + 60))  # newer past the file system's clock tick
    with pytest.raises(WouldRun, match="none"):
        gap.main(args(policy))
    with pytest.raises(ValueError, match=r"--shifts \['gravity'\]: the rows are"):
        gap.main(gap.Args(shifts=["gravity"], out=tmp_path))
    with pytest.raises(ValueError, match="correct camera frames: --camera twin"):
        gap.main(gap.Args(camera="none", shifts=["camera mount, corrected"], out=tmp_path))
    both = gap.spec_of("lighting & colours/textures")
    assert both == gap.SHIFTS["lighting"] + "," + gap.SHIFTS["colours/textures"]
    for bad in ("lighting & gravity", "lighting & camera mount, corrected", "none & lighting"):
        with pytest.raises(ValueError, match="or plain ones joined by '&'"):
            gap.main(gap.Args(shifts=["none", bad], out=tmp_path))


def test_sim2real_gap_appearance_parts_make_up_the_colours_textures_row(bench_script):
    """The three rows that split colours/textures: each one field group of it, together exactly it, each parsed to
    that part alone, and none in the default table."""
    from maniskill_irb120.envs.randomization import Randomization

    gap = bench_script("sim2real_gap")
    whole = Randomization.parse(gap.SHIFTS["colours/textures"])
    parts = {name: Randomization.parse(gap.SHIFTS[name]) for name in ("colour only", "texture only", "shine only")}
    assert gap.spec_of("colour only & texture only & shine only") == gap.SHIFTS["colours/textures"]
    assert (parts["colour only"].color, parts["colour only"].texture) == (whole.color, 0.0)
    assert (parts["texture only"].texture, parts["texture only"].color) == (whole.texture, 0.0)
    shine = parts["shine only"]
    assert (shine.roughness, shine.specular, shine.color, shine.texture) == (whole.roughness, whole.specular, 0, 0)
    assert set(parts) <= gap.BY_NAME_ONLY


def test_sim2real_gap_mount_error_rows_scale_the_mount_and_run_only_when_named(tmp_path, bench_script):
    from maniskill_irb120.envs.randomization import Randomization

    gap = bench_script("sim2real_gap")
    full = Randomization.parse(gap.SHIFTS["camera mount"])
    quarter = Randomization.parse(gap.SHIFTS["camera mount x0.25"])
    assert quarter.camera_pos == pytest.approx([v / 4 for v in full.camera_pos])
    assert quarter.camera_rot == pytest.approx([v / 4 for v in full.camera_rot])
    beyond = Randomization.parse(gap.SHIFTS["camera mount x1.25"])  # a calibration error past a measured mount
    assert beyond.camera_pos == pytest.approx([v * 1.25 for v in full.camera_pos])
    assert gap.SHIFTS["camera mount, position only"] == gap.SHIFTS["camera mount"].split(",")[0]
    assert gap.SHIFTS["camera mount, rotation only"] == gap.SHIFTS["camera mount"].split(",")[1]
    ran = []

    def evaluate(cfg):  # records each cell's configuration instead of rolling it out
        ran.append((cfg.out.name, cfg.shift, cfg.camera_mount))
        sides = dict(success=0.0, grasped=0.0, dropped=0.0, collided=0.0)
        episode = dict(sim_success=0.0, real_success=0.0)
        return dict(
            sim=sides,
            real=sides,
            deviation=dict(tcp_m=dict(mean=0.0)),
            command_latency_ms=dict(p50=0.0),
            refused=dict(total=0),
            late_steps=0,
            interrupted=False,
            per_episode=[episode],
        )

    gap.evaluate = evaluate
    gap.main(gap.Args(camera="twin", out=tmp_path))  # the default table: no calibration-error rows
    assert {name for name, _, _ in ran} == {gap.folder(n) for n in gap.SHIFTS if n not in gap.BY_NAME_ONLY}
    ran.clear()
    out = gap.main(gap.Args(camera="twin", shifts=["camera mount x0.1", "none"], out=tmp_path))
    assert ran == [("camera_mount_x0.1", gap.SHIFTS["camera mount x0.1"], None), ("none", None, None)]  # as named
    assert [row["shift"] for row in out["rows"]] == ["none", "camera mount x0.1"]  # reported in the table's order


def test_learning_recipe_flags_add_a_tasks_own_flags_there_only():
    from benchmarks import learning

    grasp, clear = (recipe_on("ppo-state", env).argv() for env in ("GraspLift-IRB120-v1", learning.DEFAULT_ENV))
    assert grasp == [*RECIPES["ppo-state"].argv(), "--logstd", "state"]
    assert clear == RECIPES["ppo-state"].argv() and "--logstd" not in clear
    assert recipe_on("sac-scratch-state", "GraspLift-IRB120-v1").argv() == RECIPES["sac-scratch-state"].argv()


def test_learning_rerun_keeps_the_earlier_run_and_reads_its_own_curve(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    run = tmp_path / "runs" / "dagger-rgbd__s1"
    with SummaryWriter(run) as w:
        w.add_scalar("train/success_rate", 0.0, 100)
    assert runner.make_room(run) == run and not run.exists()
    (old,) = (tmp_path / "runs").glob("dagger-rgbd__s1.before-*")
    assert list(old.glob("events.out.tfevents.*"))  # nothing of the earlier run is lost
    for value in (0.25, 0.75):  # a resume appends a second event file, and trains step 200 again
        with SummaryWriter(run) as w:
            w.add_scalar("train/success_rate", value, 200)
        time.sleep(0.05)
    assert runner.curve(run)["success"] == [0.75]


def test_learning_keeps_a_long_curve_as_bin_means_and_a_two_stage_runs_stages_apart(tmp_path, monkeypatch):
    """A run's curve is thinned to ``CURVE_POINTS`` bin means, each at its bin's last env step and minute, so the
    committed JSON stays small; a two-stage run joins two thinned curves, so no bin mixes teacher and student."""
    from torch.utils.tensorboard import SummaryWriter

    monkeypatch.setattr(runner, "CURVE_POINTS", 4)
    run = tmp_path / "run"
    with SummaryWriter(run) as w:
        for i in range(10):
            w.add_scalar("train/success_rate", i / 10, 100 * (i + 1))
    c = runner.curve(run)
    assert c["env_steps"] == [300, 600, 800, 1000]  # bins of 3, 3, 2 and 2 points
    assert c["success"] == pytest.approx([0.1, 0.4, 0.65, 0.85]) and len(c["wall_min"]) == 4
    short = dict(env_steps=[1, 2], wall_min=[0.1, 0.2], success=[0.0, 1.0])
    assert runner.thinned(short, points=4) == short
    base = dict(env_steps=1000, wall_clock_s=60.0, success_rate=1.0, checkpoint="b.pt", command="teach", curve=c)
    tuned = dict(base, env_steps=50, wall_clock_s=30.0, command="learn", curve=short)
    joined = runner.joined(base, tuned)["curve"]
    assert joined["env_steps"] == [300, 600, 800, 1000, 1001, 1002] and joined["success"][4:] == [0.0, 1.0]
    # the second stage's selection checks move onto the same axis
    checks = runner.joined(base, dict(tuned, selection_checks=[[25, 0.5, 3.0], [50, 1.0, 4.0]]))["selection_checks"]
    assert checks == [[1025, 0.5, 3.0], [1050, 1.0, 4.0]]


def test_learning_plot_marks_each_runs_held_out_success_where_it_ended_and_a_teachers_too(tmp_path, monkeypatch):
    """A teacher-student run's training curve sits near 0 while its student learns (the noisy learner collects),
    so the plot also puts a dot at each run's held-out success: filled at the run's end, hollow at its first
    stage's."""
    from matplotlib import pyplot

    from benchmarks import learning

    curve = dict(env_steps=[1000, 2000, 3000], wall_min=[10.0, 50.0, 120.0], success=[0.5, 0.0, 0.0])
    base = dict(success_rate=0.9, env_steps=1500, wall_clock_s=2700.0, checkpoint="teacher.pt")
    run = dict(curve=curve, success_rate=0.92, env_steps=3000, wall_clock_s=7200.0, base=base)
    rows = [dict(recipe="teacher-student-rgbd", runs=[run]), dict(recipe="expert", success_mean=1.0)]
    drawn = []
    real_savefig = pyplot.Figure.savefig

    def savefig(fig, path, *a, **k):
        drawn.extend((ax.get_xlabel(), line) for ax in fig.axes for line in ax.get_lines())
        return real_savefig(fig, path, *a, **k)

    monkeypatch.setattr(pyplot.Figure, "savefig", savefig)
    learning.plot(rows, tmp_path / "learning.png")
    dots = {
        (x, line.get_xdata()[0], line.get_ydata()[0], line.get_markerfacecolor() == "white")
        for x, line in drawn
        if line.get_marker() == "o"
    }
    steps, minutes = "env steps (thousands)", "wall clock (min)"
    assert dots == {
        (steps, 3000, 0.92, False),
        (minutes, 120.0, 0.92, False),
        (steps, 1500, 0.9, True),
        (minutes, 45.0, 0.9, True),
    }
    assert (tmp_path / "learning.png").stat().st_size > 1000


def test_learning_iqm_is_over_seeds_not_single_episodes():
    import numpy as np

    from benchmarks import learning

    runs = [dict(successes=[1] * 76 + [0] * 24, success_rate=0.76, seed=1)]
    row = learning.summarise("x", "rgbd", runs, learning.Args(bootstrap=100), np.random.default_rng(0))
    assert row["success_iqm"] == 0.76  # over the 100 episodes (0 or 1 each) it would read 1.00
    assert learning.iqm([0.1, 0.5, 0.6, 0.9]) == 0.55


def test_learning_merge_keeps_other_recipes_with_their_provenance(tmp_path):
    from benchmarks import learning

    row = dict(success_ci95=[0.9, 1.0], seeds=[1], per_seed=[0.97], success_mean=0.97, success_iqm=1.0)
    row.update(obs="state", env_steps_mean=1000, wall_clock_min_mean=60.0)
    old = dict(command="python benchmarks/learning.py --recipes dagger-state sac-state", date="2026-11-23 09:06 UTC")
    old["rows"] = [dict(row, recipe="expert"), dict(row, recipe="dagger-state"), dict(row, recipe="sac-state")]
    with pytest.raises(FileNotFoundError, match="--merge"):
        learning.carried_rows(tmp_path / "learning.json", ["dagger-rgbd"])
    (tmp_path / "learning.json").write_text(json.dumps(old))
    kept = learning.carried_rows(tmp_path / "learning.json", ["sac-state"])  # sac-state is retrained
    assert [r["recipe"] for r in kept] == ["dagger-state"]
    assert kept[0]["command"] == old["command"] and kept[0]["date"] == old["date"]
    new = dict(row, recipe="sac-state", command="python benchmarks/learning.py --recipes sac-state --merge")
    report = dict(command=new["command"], date="2026-11-24 10:00 UTC", machine="m", wall_min=120, eval_episodes=100)
    report["rows"] = [dict(row, recipe="expert"), dict(new, date=report["date"]), *kept]
    results = tmp_path / "RESULTS.md"
    results.write_text("# R\n\n## Learning — `benchmarks/learning.py`\n\nold\n\n## Next\n")
    learning.update_results(report, learning.markdown(report["rows"]), results)
    text = results.read_text()
    assert "carried over from earlier runs (`--merge`, `--adopt`): dagger-state: `python benchmarks/learning.py" in text
    assert "| sac-state | state |" in text and "| dagger-state | state |" in text and "## Next" in text
    assert "old" not in text.split("## Next")[0] and "expert: `" not in text


def test_learning_merge_gathers_a_recipes_seeds_from_several_runs(tmp_path):
    import numpy as np

    from benchmarks import learning

    first = "python benchmarks/learning.py --recipes dagger-state --seeds 2"
    runs = [dict(seed=2, success_rate=0.97, successes=[1] * 97 + [0] * 3, env_steps=10, wall_clock_s=3600.0)]
    row = learning.summarise("dagger-state", "state", runs, learning.Args(bootstrap=100), np.random.default_rng(0))
    old = dict(command=first, date="2026-11-23 09:06 UTC", rows=[dict(row, command=first, date="2026-11-23 09:06 UTC")])
    (tmp_path / "learning.json").write_text(json.dumps(old))
    assert learning.earlier_runs(tmp_path / "learning.json", "dagger-state", [2, 3]) == []  # seed 2 is retrained
    assert learning.earlier_runs(tmp_path / "learning.json", "sac-state", [1]) == []
    (kept,) = learning.earlier_runs(tmp_path / "learning.json", "dagger-state", [1, 3])
    assert kept["seed"] == 2 and kept["benchmark_command"] == first and kept["date"] == old["date"]

    date, cmd = "2026-11-24 18:30 UTC", "python benchmarks/learning.py --recipes dagger-state --seeds 1 --merge"
    new = dict(seed=1, success_rate=0.91, successes=[1] * 91 + [0] * 9, env_steps=30, wall_clock_s=3500.0)
    merged = sorted([kept, dict(new, benchmark_command=cmd, date=date)], key=lambda r: r["seed"])
    both = learning.summarise("dagger-state", "state", merged, learning.Args(bootstrap=200), np.random.default_rng(0))
    assert both["seeds"] == [1, 2] and both["per_seed"] == [0.91, 0.97] and both["env_steps_mean"] == 20
    lo, hi = both["success_ci95"]
    assert 0.87 < lo < 0.94 < hi <= 1.0
    report = dict(command=cmd, date=date, machine="m", wall_min=60, eval_episodes=100)
    report["rows"] = [dict(both, command=cmd, date=date)]
    results = tmp_path / "RESULTS.md"
    results.write_text("# R\n\n## Learning — `benchmarks/learning.py`\n\nold\n")
    learning.update_results(report, learning.markdown(report["rows"]), results)
    text = results.read_text()
    assert f"(`--merge`, `--adopt`): dagger-state seed 2: `{first}` (2026-11-23 09:06 UTC)." in text
    assert "| dagger-state | state | 2 | 0.94 |" in text


def test_sim_speed_baseline_names_a_commit_or_refuses(tmp_path, bench_script):
    mod = bench_script("sim_speed")
    with pytest.raises(SystemExit, match="not-a-ref"):
        mod.baseline_tree("not-a-ref", tmp_path)
    if IN_GIT:
        commit = mod.baseline_tree("HEAD", tmp_path)
        assert len(commit) == 40 and (tmp_path / "tree" / "maniskill_irb120" / "envs" / "base.py").is_file()


def test_floor_times_physics_substeps_and_one_rgbd_frame(bench_script):
    r = bench_script("sim_speed").measure_floor("TableClearing-IRB120-v1", steps=5, seed=0, warmup=2)
    assert len(r["times"]) == 5 and min(r["times"]) > 0
    assert r["substeps"] == 5 and r["pictures"] == ["Color", "PositionSegmentation"]


def test_batched_benchmark_loop_runs_with_auto_reset(bench_script):
    mod = bench_script("sim_speed")
    r = mod.measure_batched("TableClearing-IRB120-v1", 1, steps=260, seed=0, backend="inprocess", obs_mode="state")
    assert r["env_steps_per_s"] > 0
    assert r["episodes_finished"] >= 1  # random actions collide or time out at 250 steps: auto-reset ran
    assert not math.isnan(r["env_steps_per_s"]) and np.isfinite(r["gpu_mem_used_gb"])


def test_learning_keeps_one_section_per_task(tmp_path):
    from benchmarks import learning

    results = tmp_path / "RESULTS.md"
    results.write_text("# R\n\n## Learning — `benchmarks/learning.py`\n\ntable clearing\n\n## Next\n")
    row = dict(recipe="ppo-state", obs="state", seeds=[1], success_mean=0.5, success_ci95=[0.4, 0.6], success_iqm=0.5)
    row.update(per_seed=[0.5], env_steps_mean=10, wall_clock_min_mean=1.0, runs=[])
    report = dict(command="python benchmarks/learning.py --env-id GraspLift-IRB120-v1", date="d", machine="m")
    report.update(wall_min=1, eval_episodes=100, rows=[row], env_id="GraspLift-IRB120-v1")
    report["out_dir"] = str(learning.default_out_dir("GraspLift-IRB120-v1"))
    learning.update_results(report, learning.markdown(report["rows"]), results)
    text = results.read_text()
    assert "table clearing" in text and "## Next" in text  # TableClearing's section is left alone
    head = "## Learning on GraspLift-IRB120-v1 — `benchmarks/learning.py --env-id GraspLift-IRB120-v1`"
    assert head in text and "(results/learning/GraspLift-IRB120-v1/learning.json)" in text
    assert "| ppo-state | state | 1 | 0.50 |" in text
    with pytest.raises(ValueError, match="unknown --env-id"):
        learning.main(learning.Args(env_id="PickCube-v1"))


def test_learning_adopts_a_finished_run_only_if_the_recipe_trained_it(tmp_path):
    """A run trained by the trainer's own command in an earlier session joins the row; one with any other learning
    argument (here the batch size) is refused by name, as is a run that never finished."""
    import tyro

    from agents import dagger
    from agents.common.logging import Logger, finish
    from benchmarks import learning

    def trained(name: str, extra: list[str], seed: int) -> Path:
        flags = [*RECIPES["dagger-rgbd-bf16"].argv(), "--budget-min", "60", "--seed", str(seed), *extra]
        args = tyro.cli(dagger.Args, args=[*flags, "--runs-dir", str(tmp_path), "--exp-name", name, "--no-progress"])
        run_dir = tmp_path / name
        log = Logger(run_dir, args)
        log.scalars({"train/success_rate": 0.5}, 1000)
        log.close()
        finish(dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=1000, wall_clock_s=3600.0), run_dir)
        return run_dir

    args = learning.Args(recipes=["dagger-rgbd-bf16"], seeds=[], out_dir=tmp_path)
    run = learning.adopted_run("dagger-rgbd-bf16", trained("ok", [], seed=2), args)
    assert run["seed"] == 2 and run["success_rate"] == 0.9 and run["adopted_from"].endswith("ok")
    assert run["curve"]["success"] == [0.5] and run["curve"]["env_steps"] == [1000]
    assert "--precision auto" in run["benchmark_command"] and "--seed 2" in run["benchmark_command"]
    with pytest.raises(ValueError, match=r"not trained by the dagger-rgbd-bf16 recipe: batch_size=32"):
        learning.adopted_run("dagger-rgbd-bf16", trained("other", ["--batch-size", "32"], seed=3), args)
    with pytest.raises(ValueError, match="budget_min=60.0 \\(the recipe's: 30.0\\)"):
        learning.adopted_run("dagger-rgbd-bf16", tmp_path / "ok", learning.Args(budget_min=30))
    # a budget typed to two decimals (a second stage's: the total less the first's wall clock) is the recipe's
    assert learning.adopted_run("dagger-rgbd-bf16", tmp_path / "ok", learning.Args(budget_min=59.99))["seed"] == 2
    with pytest.raises(ValueError, match="budget_min=60.0 \\(the recipe's: 59.98\\)"):
        learning.adopted_run("dagger-rgbd-bf16", tmp_path / "ok", learning.Args(budget_min=59.98))
    (tmp_path / "ok" / "summary.json").unlink()
    with pytest.raises(FileNotFoundError, match="no summary.json"):
        learning.adopted_run("dagger-rgbd-bf16", tmp_path / "ok", args)


def test_learning_adopts_a_run_resumed_across_sessions_whole_and_only_with_its_own_arguments(tmp_path):
    """A run the session's end cut short and ``--resume`` continued: both sessions' points make its curve; a session
    that continued it with another learning argument is refused by name."""
    import tyro

    from agents import dagger
    from agents.common.logging import Logger, finish
    from benchmarks import learning

    flags = [*RECIPES["dagger-rgbd-bf16"].argv(), "--budget-min", "60", "--seed", "2", "--no-progress"]
    args = tyro.cli(dagger.Args, args=[*flags, "--runs-dir", str(tmp_path), "--exp-name", "cut"])
    run_dir = tmp_path / "cut"
    for session, (step, value) in enumerate(((1000, 0.5), (2000, 0.7))):
        resumed = dict(resume=run_dir / "checkpoints" / "latest.pt") if session else {}
        log = Logger(run_dir, replace(args, **resumed))
        log.scalars({"train/success_rate": value}, step)
        log.close()
        time.sleep(0.05)
    finish(dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=2000, wall_clock_s=3600.0), run_dir)
    largs = learning.Args(recipes=["dagger-rgbd-bf16"], seeds=[], out_dir=tmp_path)
    run = learning.adopted_run("dagger-rgbd-bf16", run_dir, largs)
    assert run["curve"]["env_steps"] == [1000, 2000] and run["curve"]["success"] == pytest.approx([0.5, 0.7])
    log = Logger(run_dir, replace(args, batch_size=32, resume=run_dir / "checkpoints" / "latest.pt"))
    log.close()
    with pytest.raises(ValueError, match=r"continued .*cut with other arguments: batch_size=32"):
        learning.adopted_run("dagger-rgbd-bf16", run_dir, largs)


def test_learning_adopts_a_ppo_run_that_kept_other_periodic_checkpoints(tmp_path):
    """--keep-checkpoints decides which files stay on disk, not what the run learns: a run started keeping every
    checkpoint and resumed keeping the default is the recipe's run (the camera run of the original report's
    experiment was started before the flag existed)."""
    import tyro

    from agents import ppo
    from agents.common.logging import Logger, finish
    from benchmarks import learning

    flags = [*RECIPES["ppo-state"].argv(), "--budget-min", "30", "--eval-episodes", "100", "--seed", "2"]
    flags += ["--runs-dir", str(tmp_path), "--exp-name", "kept", "--no-progress", "--keep-checkpoints", "0"]
    args = tyro.cli(ppo.Args, args=flags)
    run_dir = tmp_path / "kept"
    for session, step in enumerate((1000, 2000)):
        resumed = dict(resume=run_dir / "checkpoints" / "latest.pt", keep_checkpoints=5) if session else {}
        log = Logger(run_dir, replace(args, **resumed))
        log.scalars({"train/success_rate": 0.5}, step)
        log.close()
        time.sleep(0.05)
    finish(dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=2000, wall_clock_s=1800.0), run_dir)
    largs = learning.Args(recipes=["ppo-state"], seeds=[], out_dir=tmp_path, rl_budget_min=30)
    run = learning.adopted_run("ppo-state", run_dir, largs)
    assert run["seed"] == 2 and run["curve"]["env_steps"] == [1000, 2000]


def test_learning_reads_a_field_a_runs_log_predates_as_its_default(tmp_path, monkeypatch):
    """A run trained before a trainer gained a flag logged no value for it: it ran with what is now the default, so
    the recipe's run is adopted, whether the flag is missing from every session's log or only from the first's; a
    logged value other than the recipe's is still refused."""
    import tyro

    from agents import dagger
    from agents.common.logging import Logger, finish
    from benchmarks import learning

    flags = [*RECIPES["dagger-rgbd-bf16"].argv(), "--budget-min", "60", "--seed", "2", "--eval-episodes", "100"]
    args = tyro.cli(dagger.Args, args=[*flags, "--runs-dir", str(tmp_path), "--exp-name", "old", "--no-progress"])
    run_dir = tmp_path / "old"
    for session, step in enumerate((1000, 2000)):
        resumed = dict(resume=run_dir / "checkpoints" / "latest.pt") if session else {}
        log = Logger(run_dir, replace(args, **resumed))
        log.scalars({"train/success_rate": 0.5}, step)
        log.close()
        time.sleep(0.05)
    finish(dict(success_rate=0.9, successes=[1] * 9 + [0], env_steps=2000, wall_clock_s=3600.0), run_dir)
    read = adopt.logged_args
    first = adopt.event_files(run_dir)[0]

    def predating(events, keep_first=False):
        logged, opened = read(events)
        if events == first or not keep_first:
            logged = {k: v for k, v in logged.items() if k not in ("select_episodes", "select_freq")}
        return logged, opened

    largs = learning.Args(recipes=["dagger-rgbd-bf16"], seeds=[], out_dir=tmp_path)
    for keep_first in (False, True):  # the flag missing from both sessions' logs, or from the first's only
        monkeypatch.setattr(adopt, "logged_args", lambda e, k=keep_first: predating(e, k))
        assert learning.adopted_run("dagger-rgbd-bf16", run_dir, largs)["seed"] == 2
    monkeypatch.setattr(adopt, "logged_args", read)
    log = Logger(run_dir, replace(args, select_episodes=30, resume=run_dir / "checkpoints" / "latest.pt"))
    log.close()
    with pytest.raises(ValueError, match=r"continued .*old with other arguments: select_episodes=30 \(first: 0\)"):
        learning.adopted_run("dagger-rgbd-bf16", run_dir, largs)


def test_learning_adopts_a_sac_run_whose_log_holds_its_resolved_buffer_size(tmp_path):
    """agents.sac logs --buffer-size filled in (300,000 from state), the recipe leaves it to the trainer: the
    run is the recipe's; one that kept another buffer is not."""
    import tyro

    from agents import sac
    from agents.common.logging import Logger, finish
    from benchmarks import learning

    def trained(name: str, extra: list[str]) -> Path:
        flags = [*RECIPES["sac-scratch-state"].argv(), "--env-id", "GraspLift-IRB120-v1", "--budget-min", "90"]
        args = tyro.cli(sac.Args, args=[*flags, *extra, "--runs-dir", str(tmp_path), "--exp-name", name])
        run_dir = tmp_path / name
        log = Logger(run_dir, sac.resolved(args))  # as agents.sac's train() logs it
        log.close()
        finish(dict(success_rate=0.0, successes=[0] * 10, env_steps=1000, wall_clock_s=5400.0), run_dir)
        return run_dir

    args = learning.Args(
        recipes=["sac-scratch-state"], seeds=[], out_dir=tmp_path, env_id="GraspLift-IRB120-v1", rl_budget_min=90
    )
    assert learning.adopted_run("sac-scratch-state", trained("ok", []), args)["success_rate"] == 0.0
    with pytest.raises(ValueError, match=r"buffer_size=1000 \(the recipe's: 300000\)"):
        learning.adopted_run("sac-scratch-state", trained("small", ["--buffer-size", "1000"]), args)


def test_sim2real_gap_runs_each_policy_on_its_own_task(bench_script):
    gap = bench_script("sim2real_gap")
    assert gap.task_of("expert", gap.Args()) == "TableClearing-IRB120-v1"
    assert gap.task_of("teacher-student-grasplift-s1", gap.Args()) == "GraspLift-IRB120-v1"  # from its checkpoint
    forced = gap.Args(env_id="StackCube-IRB120-v1")
    assert gap.task_of("teacher-student-grasplift-s1", forced) == "StackCube-IRB120-v1"  # load_policy refuses it later


def test_sim2real_gap_leaves_an_unreadable_checkpoint_to_the_evaluation(tmp_path, bench_script):
    gap = bench_script("sim2real_gap")
    bogus = tmp_path / "policy.pt"
    bogus.write_bytes(b"weights")
    assert gap.task_of(str(bogus), gap.Args()) == "TableClearing-IRB120-v1"
    with pytest.raises(Exception, match="policy.pt"):  # the cell's evaluation names the file it cannot read
        gap.evaluate(gap.EvalConfig(policy=str(bogus), episodes=1, out=tmp_path / "cell"))


def test_the_collision_scripts_default_shift_is_the_benchmarks_combined_row(bench_script):
    """scripts/collision_frames.py replays sim2real_gap's first COMBINED row without importing the benchmarks."""
    import importlib.util

    gap = bench_script("sim2real_gap")
    spec = importlib.util.spec_from_file_location("collision_frames", REPO / "scripts" / "collision_frames.py")
    frames = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(frames)
    assert frames.COMBINED == gap.COMBINED["fov 75 + light 0.5 + colours/textures + D435"]


def test_rllib_speed_gives_our_trainer_back_the_torch_setting_rllib_seeding_turned_on():
    """RLlib's seeding turns on torch's deterministic algorithms for the whole process on a CPU build; the benchmark
    lets RLlib keep it while RLlib runs and puts it back after, so agents.ppo's turns in the same process run as
    agents.ppo runs alone."""
    pytest.importorskip("ray")
    import torch
    from ray.rllib.utils.torch_utils import set_torch_seed

    from benchmarks import rllib_speed

    before = torch.are_deterministic_algorithms_enabled()
    with rllib_speed.own_torch_determinism():
        set_torch_seed(1)
        assert torch.are_deterministic_algorithms_enabled() or torch.version.cuda is not None
    assert torch.are_deterministic_algorithms_enabled() == before
