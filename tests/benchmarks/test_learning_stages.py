"""Two-stage recipes (a base run whose checkpoint the second stage starts from or imitates) adopted from runs trained
by the trainers' own commands, as teacher-student-rgbd is across sessions."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import pytest
import tyro

from agents import dagger, ppo
from agents.common.logging import Logger, finish
from agents.recipes import RECIPES
from agents.recipes import recipe as recipe_on
from benchmarks import learning
from benchmarks.lib import machine, runner

REPO = Path(__file__).resolve().parents[2]

ENV = "GraspLift-IRB120-v1"


def trained(
    tmp_path: Path, module, recipe: str, name: str, extra: list[str], wall_s: float, steps: int, env: str = ENV
) -> Path:
    """A finished run of ``recipe``'s flags plus ``extra``, as the trainer logs and summarises it."""
    flags = [*recipe_on(recipe, env).argv(), "--env-id", env, "--eval-episodes", "100", *extra]
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
    share = RECIPES["teacher-student-rgbd"].base.share
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

    tc = "TableClearing-IRB120-v1"
    assert (
        recipe_on("teacher-student-rgbd-sel", tc).base.share == 0.6
        and recipe_on("teacher-student-rgbd", tc).base.share == 0.375
    )
    assert recipe_on("teacher-student-rgbd-sel", ENV).base.share == 0.375
    student_flags = recipe_on("teacher-student-rgbd-sel", tc).argv()
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
    from benchmarks import original_experiment as oe

    args = oe.Args(runs_dir=tmp_path, out_dir=tmp_path)
    assert "--resume" not in oe.command("ppo-rgbd-dense", args)
    latest = oe.run_dir("ppo-rgbd-dense", args) / "checkpoints" / "latest.pt"
    latest.parent.mkdir(parents=True)
    latest.write_bytes(b"")
    cmd = oe.command("ppo-rgbd-dense", args)
    assert cmd[cmd.index("--resume") + 1] == str(latest) and cmd[cmd.index("--reward-mode") + 1] == "dense"
    assert "--resume" not in oe.command("ppo-rgbd-dense", args, resume=False)  # the report's: from the start
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

    cmd = [sys.executable, "-m", "benchmarks.original_experiment", "--quick"]
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


@pytest.mark.parametrize("parent_sigint", ["default", "ignored"])
def test_a_trainer_is_interrupted_at_the_deadline_and_gives_its_output(tmp_path, parent_sigint):
    """runner.run_until: at the deadline the trainer gets SIGINT, its Ctrl-C (which saves its checkpoint), and the
    run counts as unfinished; before it, the trainer's own exit code comes back. "ignored": a script's ``cmd &``
    starts the benchmark with SIGINT ignored, which the trainer would inherit and so never save at the deadline;
    run_until gives the trainer SIGINT's default back."""
    import signal

    code = (
        "import signal, sys, time\n"
        "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler, flush=True)\n"
        "try:\n    time.sleep(30)\n"
        "except KeyboardInterrupt:\n    print('checkpoint saved', flush=True); sys.exit(1)\n"
    )
    before = signal.signal(signal.SIGINT, signal.SIG_IGN) if parent_sigint == "ignored" else None
    try:
        t0 = time.time()
        out, err, rc = runner.run_until([sys.executable, "-c", code], deadline=time.time() + 1.0)
    finally:
        if before is not None:
            signal.signal(signal.SIGINT, before)
    assert rc is None and out.split() == ["True", "checkpoint", "saved"] and time.time() - t0 < 20, (out, err)
    out, err, rc = runner.run_until([sys.executable, "-c", "print(7)"], deadline=time.time() + 30)
    assert (out.strip(), rc) == ("7", 0)


@pytest.mark.skipif(not Path("/proc/self/autogroup").is_file(), reason="no scheduler autogroups on this kernel")
def test_a_niced_benchmark_keeps_its_trainer_niced_in_the_new_session():
    """A trainer runs in its own session, and Linux gives a new session its own autogroup at nice 0, which the
    scheduler weighs before the nice value: a benchmark under ``nice -n 5`` would have run its trainer at a full
    share. run_until carries the benchmark's niceness into the trainer's autogroup; without it this reads 0."""
    import os
    import subprocess

    ours = os.nice(0)  # the suite's own niceness, which `nice -n 5` adds to
    code = (
        "import sys, time; from benchmarks.lib import runner\n"
        "out, err, rc = runner.run_until(['cat', '/proc/self/autogroup'], deadline=time.time() + 60)\n"
        "print(out.strip())\n"
    )
    root = Path(runner.__file__).resolve().parents[2]
    got = subprocess.run(["nice", "-n", "5", sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert got.returncode == 0, got.stderr[-2000:]
    assert got.stdout.strip().endswith(f"nice {min(ours + 5, 19)}"), got.stdout
    # and a benchmark at the suite's priority: the same in the trainer's session (0, its default, when not niced)
    got = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert got.stdout.strip().endswith(f"nice {ours}"), got.stdout


FAKE_TRAINER = """
import signal, sys, time
from pathlib import Path
out = Path(sys.argv[1])
def on_int(*_):  # a trainer's Ctrl-C: it saves its checkpoint, slowly, then exits
    with open(out / "sigint", "a") as f:
        f.write("1")
    time.sleep(1.0)
    (out / "saved").write_text("yes")
    print("checkpoint saved", flush=True)
    sys.exit(1)
signal.signal(signal.SIGINT, on_int)
(out / "started").write_text("yes")
time.sleep(60)
"""

DRIVER = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C as at a terminal, even if pytest runs in a job
sys.path.insert(0, sys.argv[1])
from benchmarks.lib import runner
try:
    runner.run_until([sys.executable, "-c", sys.argv[2], sys.argv[3]], deadline=None)
    print("not interrupted")
except runner.Interrupted as stop:
    print("interrupted:", stop.args[0].strip())
"""


def started(path: Path, timeout: float = 180.0) -> None:
    """Wait for ``path``: the driver imports learning (torch) first, which took 44-63 s on a loaded 2-core VM."""
    t0 = time.time()
    while not path.exists():
        assert time.time() - t0 < timeout, f"{path} never appeared"
        time.sleep(0.05)


@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM"])
def test_a_ctrl_c_reaches_the_trainer_once_and_waits_for_its_checkpoint(tmp_path, signum):
    """A Ctrl-C (or SIGTERM) on the benchmark, not on the trainer (its own session): the trainer gets one SIGINT and
    its save is waited for, a second Ctrl-C during the save is ignored, and run_until raises Interrupted with its
    output. subprocess.run would have killed the trainer 0.25 s after the Ctrl-C."""
    import signal
    import subprocess

    driver = subprocess.Popen(
        [sys.executable, "-c", DRIVER, str(REPO), FAKE_TRAINER, str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    started(tmp_path / "started")
    driver.send_signal(getattr(signal, signum))
    started(tmp_path / "sigint", timeout=10)
    driver.send_signal(signal.SIGINT)  # impatient: during the save
    out, err = driver.communicate(timeout=30)
    assert driver.returncode == 0, err[-2000:]
    assert "interrupted: checkpoint saved" in out and (tmp_path / "saved").read_text() == "yes"
    assert (tmp_path / "sigint").read_text() == "1"  # one SIGINT, not two


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_benchmark_leaves_no_trainer_training(tmp_path):
    """SIGKILL on the benchmark: its trainer gets SIGINT (and saves) rather than training on unwatched."""
    import signal
    import subprocess

    driver = subprocess.Popen(
        [sys.executable, "-c", DRIVER, str(REPO), FAKE_TRAINER, str(tmp_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    started(tmp_path / "started")
    driver.send_signal(signal.SIGKILL)
    driver.wait(timeout=10)
    started(tmp_path / "saved", timeout=10)
    assert (tmp_path / "sigint").read_text() == "1"


def test_a_ctrl_c_keeps_the_finished_seeds_and_starts_no_other(tmp_path, monkeypatch):
    """learning.main interrupted during seed 2: seed 1's run goes into the report, seed 3 never starts, and the exit
    status is a Ctrl-C's (130), so a chain of commands stops."""
    import json

    def run(seed):
        return dict(seed=seed, success_rate=0.9, successes=[1] * 9 + [0], env_steps=100, wall_clock_s=60.0,
                    curve=dict(env_steps=[], wall_min=[], success=[]))  # fmt: skip

    calls = []

    def fake_train(recipe, seed, args, deadline):
        calls.append(seed)
        if seed == 2:
            raise learning.Interrupted("", "")
        return run(seed)

    timings = iter([100.0, 90.0, 80.0])  # the reference workload before and after seed 1, before seed 2

    monkeypatch.setattr(learning, "train_run", fake_train)
    monkeypatch.setattr(learning, "reference_speed", lambda steps, quick: next(timings))
    monkeypatch.setattr(learning, "reference", lambda name, args: dict(run(0), success_rate=0.0, successes=[0] * 10))
    args = learning.Args(recipes=["ppo-state"], seeds=[1, 2, 3], out_dir=tmp_path, bootstrap=50)
    with pytest.raises(SystemExit) as stop:
        learning.main(args)
    assert stop.value.code == 130 and calls == [1, 2]
    (row,) = [r for r in json.loads((tmp_path / "learning.json").read_text())["rows"] if r["recipe"] == "ppo-state"]
    assert row["seeds"] == [1] and row["runs"][0]["reference_sps"] == [100.0, 90.0]

    # a Ctrl-C while the reference is timed after a run: the run is kept, without it, and no other starts
    def interrupted_after(steps, quick):
        if len(calls) == 1:
            raise KeyboardInterrupt
        return 100.0

    calls.clear()
    monkeypatch.setattr(learning, "reference_speed", interrupted_after)
    with pytest.raises(SystemExit) as stop:
        learning.main(dataclasses.replace(args, out_dir=tmp_path / "again"))
    assert stop.value.code == 130 and calls == [1]
    (row,) = [
        r for r in json.loads((tmp_path / "again" / "learning.json").read_text())["rows"] if r["recipe"] == "ppo-state"
    ]
    assert row["seeds"] == [1] and "reference_sps" not in row["runs"][0]


def test_the_original_experiment_on_ctrl_c_keeps_the_trainers_output_and_starts_no_other_run(tmp_path, monkeypatch):
    """original_experiment.py runs its trainers as runner.run_until does: a Ctrl-C during the first run keeps that
    trainer's output in its log, starts no second run, writes the report with where each run stands, and exits 130."""
    import json

    from benchmarks import original_experiment as oe

    # the learning module that original_experiment imported: another test's bench_script("learning") may have put a
    # fresh one in sys.modules since this file imported its own, and each has its own Interrupted class
    used = oe.run_logged.__globals__
    calls = []

    def interrupted(cmd, deadline):
        calls.append(cmd)
        raise used["Interrupted"]("saved latest.pt", "KeyboardInterrupt")

    monkeypatch.setitem(used, "run_until", interrupted)
    args = oe.Args(runs_dir=tmp_path / "runs", out_dir=tmp_path)
    with pytest.raises(SystemExit) as stop:
        oe.main(args)
    assert stop.value.code == 130 and len(calls) == 1 and "--reward-mode" in calls[0]  # the report's reward first
    report = json.loads((tmp_path / "original_experiment.json").read_text())
    assert report["status"] == {"ppo-rgbd-dense": "stopped", "ppo-rgbd": "not started"}
    log = (tmp_path / "runs" / "logs" / f"{oe.run_dir('ppo-rgbd-dense', args).name}.log").read_text()
    assert "saved latest.pt" in log and "KeyboardInterrupt" in log
    # at the deadline the trainer's exit is "stopped", and the run continues next time; a failure names its log
    monkeypatch.setitem(used, "run_until", lambda cmd, deadline: ("out", "err", None))
    assert oe.train("ppo-rgbd", args, deadline=time.time() + 60) == "stopped"
    monkeypatch.setitem(used, "run_until", lambda cmd, deadline: ("out", "Traceback", 1))
    with pytest.raises(RuntimeError, match=r"ppo-rgbd exited with 1; its output is in .*\.log"):
        oe.train("ppo-rgbd", args, deadline=None)


def test_a_session_stopped_early_keeps_only_finished_seeds_and_earlier_runs_of_the_others(tmp_path, monkeypatch):
    """learning.main with --stop-after-min: a seed cut short adds no run (the same command continues it), its
    earlier run in the report stays until its new one finishes, and a finished seed replaces its earlier run."""
    import json

    import numpy as np

    def run(seed, rate):
        return dict(seed=seed, success_rate=rate, successes=[1] * int(rate * 10) + [0] * (10 - int(rate * 10)),
                    env_steps=100, wall_clock_s=60.0, curve=dict(env_steps=[], wall_min=[], success=[]))  # fmt: skip

    old_runs = [run(1, 0.5), run(2, 0.5)]
    old_row = learning.summarise("ppo-state", "state", old_runs, learning.Args(bootstrap=50), np.random.default_rng(0))
    (tmp_path / "learning.json").write_text(json.dumps(dict(command="old", date="d", rows=[old_row])))
    calls = []

    def fake_train(recipe, seed, args, deadline):
        calls.append((recipe, seed, deadline is not None))
        return run(seed, 0.9) if seed == 1 else None  # seed 2 cut short by the deadline

    monkeypatch.setattr(learning, "train_run", fake_train)
    monkeypatch.setattr(learning, "reference", lambda name, args: run(0, 0.0))
    for seed in (1, 2):  # the runs this machine holds, as a session that trains them leaves them
        (tmp_path / "runs" / f"ppo-state__s{seed}").mkdir(parents=True)
    args = learning.Args(recipes=["ppo-state"], seeds=[1, 2], out_dir=tmp_path, merge=True, stop_after_min=5.0,
                         reference_steps=0)  # fmt: skip
    report = learning.main(dataclasses.replace(args, bootstrap=50))
    assert calls == [("ppo-state", 1, True), ("ppo-state", 2, True)]
    (row,) = [r for r in report["rows"] if r["recipe"] == "ppo-state"]
    assert row["seeds"] == [1, 2] and row["per_seed"] == [0.9, 0.5]  # seed 2's earlier run stays
    assert row["runs"][1]["benchmark_command"] == "old"
    with pytest.raises(FileNotFoundError, match="--merge: no earlier report"):  # before any training
        learning.main(dataclasses.replace(args, out_dir=tmp_path / "none"))
    assert len(calls) == 2
    before = (tmp_path / "learning.json").read_text()
    nothing = learning.main(dataclasses.replace(args, seeds=[2], bootstrap=50))  # no run finished: no new report
    assert nothing == {"unfinished": ["ppo-state seed 2"]} and (tmp_path / "learning.json").read_text() == before


def test_a_continued_session_on_a_machine_without_the_runs_keeps_the_reported_seeds(tmp_path, monkeypatch):
    """--merge with --stop-after-min on a fresh clone: a seed in the report whose run folders this machine lacks is
    kept as reported, not trained again; a seed with a run folder here (a two-stage recipe's first stage counts) is
    continued, and without --stop-after-min every seed is trained again."""
    import json

    import numpy as np

    def run(seed, rate=0.5):
        return dict(seed=seed, success_rate=rate, successes=[1] * int(rate * 10) + [0] * (10 - int(rate * 10)),
                    env_steps=100, wall_clock_s=60.0, curve=dict(env_steps=[], wall_min=[], success=[]))  # fmt: skip

    recipe = "teacher-student-rgbd-sel"
    old_row = learning.summarise(
        recipe, "rgbd", [run(1), run(2)], learning.Args(bootstrap=50), np.random.default_rng(0)
    )
    old_row["runs"][0]["date"] = "2026-12-02 08:13 UTC"
    (tmp_path / "learning.json").write_text(json.dumps(dict(command="old", date="d", rows=[old_row])))
    (tmp_path / "runs" / f"{recipe}__s2__base").mkdir(parents=True)  # seed 2's teacher is on this machine
    calls = []
    monkeypatch.setattr(learning, "train_run", lambda r, seed, a, d: calls.append(seed) or run(seed, 0.9))
    monkeypatch.setattr(learning, "reference", lambda name, args: run(0, 0.0))
    args = learning.Args(recipes=[recipe], seeds=[1, 2, 3], out_dir=tmp_path, merge=True, stop_after_min=5.0,
                         reference_steps=0)  # fmt: skip
    report = learning.main(dataclasses.replace(args, bootstrap=50))
    assert calls == [2, 3]
    (row,) = [r for r in report["rows"] if r["recipe"] == recipe]
    assert row["seeds"] == [1, 2, 3] and row["per_seed"] == [0.5, 0.9, 0.9]
    assert row["runs"][0]["date"] == "2026-12-02 08:13 UTC"  # seed 1 as it was reported
    calls.clear()
    learning.main(dataclasses.replace(args, stop_after_min=None, bootstrap=50))
    assert calls == [1, 2, 3]


def test_a_run_finished_in_an_earlier_session_keeps_its_reported_reference_and_date(tmp_path, monkeypatch):
    """A continued session that finds a run finished in its folder reads it again, times no reference for it (nothing
    of it trains now) and keeps the reference speed, date and command the session that trained it reported; a seed
    trained now gets this session's."""
    import json

    import numpy as np

    def run(seed, rate=0.5):
        return dict(seed=seed, success_rate=rate, successes=[1] * int(rate * 10) + [0] * (10 - int(rate * 10)),
                    env_steps=100, wall_clock_s=60.0, curve=dict(env_steps=[], wall_min=[], success=[]))  # fmt: skip

    old_row = learning.summarise("ppo-state", "state", [run(1)], learning.Args(bootstrap=50), np.random.default_rng(0))
    old_row["runs"][0].update(reference_sps=[990.0, 980.0], date="2026-12-02 08:13 UTC", benchmark_command="then")
    (tmp_path / "learning.json").write_text(json.dumps(dict(command="old", date="d", rows=[old_row])))
    (tmp_path / "runs" / "ppo-state__s1").mkdir(parents=True)
    (tmp_path / "runs" / "ppo-state__s1" / "summary.json").write_text("{}")  # seed 1 finished on this machine
    timings = iter([250.0, 240.0])
    monkeypatch.setattr(learning, "train_run", lambda r, seed, a, d: run(seed))
    monkeypatch.setattr(learning, "reference_speed", lambda steps, quick: next(timings))
    monkeypatch.setattr(learning, "reference", lambda name, args: run(0, 0.0))
    args = learning.Args(recipes=["ppo-state"], seeds=[1, 2], out_dir=tmp_path, merge=True, stop_after_min=5.0,
                         bootstrap=50)  # fmt: skip
    report = learning.main(args)
    (row,) = [r for r in report["rows"] if r["recipe"] == "ppo-state"]
    first, second = row["runs"]
    assert first["reference_sps"] == [990.0, 980.0] and first["date"] == "2026-12-02 08:13 UTC"
    assert first["benchmark_command"] == "then"
    assert second["reference_sps"] == [250.0, 240.0] and second["date"] != first["date"]
    assert not learning.finished_earlier("ppo-state", 1, dataclasses.replace(args, stop_after_min=None))


@pytest.mark.slow
def test_a_run_stopped_by_the_session_continues_where_it_stopped(tmp_path):
    """benchmarks/learning.py --stop-after-min, twice: the first session's PPO run is interrupted at its checkpoint
    and gives no row; the same command continues it to its budget, and the row's run has both sessions' steps."""
    import json
    import subprocess

    cmd = [sys.executable, "-m", "benchmarks.learning", "--env-id", ENV, "--recipes", "ppo-state"]
    cmd += ["--seeds", "1", "--rl-budget-min", "1", "--eval-episodes", "2", "--bootstrap", "100"]
    cmd += ["--out-dir", str(tmp_path)]
    first = subprocess.run([*cmd, "--stop-after-min", "0.6"], capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "unfinished, continued by the same command: ppo-state seed 1" in first.stdout
    assert not (tmp_path / "learning.json").exists()  # nothing finished: no report is written
    latest = tmp_path / "runs" / "ppo-state__s1" / "checkpoints" / "latest.pt"
    import torch

    steps_then = torch.load(latest, weights_only=False)["counters"]["env_steps"]
    assert steps_then > 0
    again = subprocess.run([*cmd, "--stop-after-min", "60"], capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "--resume" in again.stdout and "unfinished" not in again.stdout
    (row,) = [r for r in json.loads((tmp_path / "learning.json").read_text())["rows"] if r["recipe"] == "ppo-state"]
    assert row["runs"][0]["env_steps"] > steps_then and "--resume" not in row["runs"][0]["command"]
    assert 55 < row["runs"][0]["wall_clock_s"] < 60 + 30  # one budget over both sessions
    third = subprocess.run([*cmd, "--stop-after-min", "60"], capture_output=True, text=True, timeout=600)
    assert "finished earlier, read from" in third.stdout  # nothing trained again


def test_the_original_experiment_keeps_a_reported_run_whose_folder_is_not_here(tmp_path, monkeypatch):
    """On a fresh clone (no run folders) --no-train and a --stop-after-min session keep the committed runs as the
    report has them, rather than writing empty curves over them; without either flag the runs train from the start."""
    import json
    import shutil

    from benchmarks import original_experiment as oe

    shutil.copy(REPO / "benchmarks" / "results" / "original_experiment.json", tmp_path)
    before = json.loads((tmp_path / "original_experiment.json").read_text())["runs"]
    assert all(run["finished"] and run["curve"]["env_steps"] for run in before.values())
    used = oe.run_logged.__globals__
    calls = []
    monkeypatch.setitem(used, "run_until", lambda cmd, deadline: calls.append(cmd) or ("", "", None))
    for flags in (dict(train=False), dict(stop_after_min=60.0)):
        report = oe.main(oe.Args(runs_dir=tmp_path / "runs", out_dir=tmp_path, **flags))
        assert report["runs"] == before and not calls
        assert report["status"] == {recipe: "kept from the report" for recipe in oe.EXPERIMENT}
        assert json.loads((tmp_path / "original_experiment.json").read_text())["runs"] == before
    report = oe.main(oe.Args(runs_dir=tmp_path / "runs", out_dir=tmp_path))
    assert len(calls) == 2 and all("--resume" not in cmd for cmd in calls)
    assert report["status"] == {recipe: "stopped" for recipe in oe.EXPERIMENT}


def test_a_run_records_the_cpu_time_the_host_stole_while_it_trained(tmp_path, monkeypatch):
    """On a shared host the hypervisor can take a VM's CPUs (steal): a budgeted run then gets fewer env steps in its
    minutes with nothing on the machine to show why, so each run keeps the share stolen while it trained."""
    snapshots = iter([(100, 1000), (400, 2000)])  # (steal, total) ticks before and after: 300 of 1000 stolen
    monkeypatch.setattr(machine, "cpu_times", lambda: next(snapshots))
    result = dict(success_rate=1.0, successes=[1], env_steps=10, wall_clock_s=1.0)
    monkeypatch.setattr(runner, "run_logged", lambda *a, **k: (json.dumps(result), 0))
    monkeypatch.setattr(runner, "curve", lambda run_dir: {})
    args = learning.Args(recipes=["ppo-state"], seeds=[], out_dir=tmp_path, env_id=ENV)
    run = runner.run_trainer("r", "agents.ppo", [], 1, 1.0, args)
    assert run["cpu_steal"] == 0.3 and run["env_steps"] == 10
    # a two-stage run: each stage's share, and both stages' weighted by their minutes
    stage = dict(
        success_rate=1.0, env_steps=10, checkpoint="c", command="x", curve=dict(env_steps=[], wall_min=[], success=[])
    )
    both = runner.joined(dict(stage, wall_clock_s=60.0, cpu_steal=0.4), dict(stage, wall_clock_s=30.0, cpu_steal=0.1))
    assert both["cpu_steal"] == 0.3 and both["base"]["cpu_steal"] == 0.4
    assert "cpu_steal" not in runner.joined(
        dict(stage, wall_clock_s=60.0), dict(stage, wall_clock_s=30.0, cpu_steal=0.1)
    )
    # what Linux's /proc/stat gives: every field counted, steal the eighth
    stat = tmp_path / "stat"
    stat.write_text("cpu  10 0 5 80 1 0 0 4 0 0\ncpu0 5 0 2 40 0 0 0 2 0 0\n")
    monkeypatch.undo()
    real = machine.Path
    monkeypatch.setattr(machine, "Path", lambda p: stat if p == "/proc/stat" else real(p))
    assert machine.cpu_times() == (4, 100)
    assert machine.steal_fraction((4, 100), (4, 100)) is None and machine.steal_fraction(None, (4, 100)) is None
    stat.write_text("intr 1 2\n")
    assert machine.cpu_times() is None  # not Linux's format: unknown, not 0


def test_the_reference_workload_times_this_machine_and_refuses_a_negative_count(tmp_path):
    """The fixed workload each run and algorithm cell is timed against: env steps/s now, none when not asked for."""
    assert learning.reference_speed(10, quick=True) > 0
    assert learning.reference_speed(0) is None
    with pytest.raises(ValueError, match="reference steps must be >= 0"):
        learning.reference_speed(-1)
    with pytest.raises(ValueError, match="--reference-steps must be >= 0"):
        learning.main(learning.Args(recipes=["ppo-state"], reference_steps=-1, out_dir=tmp_path, env_id=ENV))
