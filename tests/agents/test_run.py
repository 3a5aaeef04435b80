"""The run scaffold every trainer shares (agents/common/run.py): one budget clock across --resume, the run's folder
and seeding, the checkpoint's common part and its restore, and the held-out evaluation's settings."""

from __future__ import annotations

import random
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.common import RunArgs, run
from agents.common.run import (
    Budget,
    Clock,
    check_resume_signature,
    checkpoint,
    close_and_save,
    held_out_evaluation,
    open_run,
    restore,
)


@dataclass
class Args(RunArgs):
    obs: str = "state"
    action_frame: str = "world"


@dataclass
class HidingArgs(Args):
    obs_without: tuple[str, ...] = ("agent/qvel",)


def test_the_clock_counts_the_time_before_a_resume_and_this_sessions():
    clock = Clock(before=100.0)
    time.sleep(0.05)
    assert 0.05 <= clock.session() < 5 and 100.05 <= clock() < clock.session() + 100.001
    clock.before = 3.0  # a trainer learns what it resumes only after its clock started
    assert 3.05 <= clock() < 8


def test_a_new_run_gets_its_own_folder_and_a_resumed_one_its_checkpoints(tmp_path):
    args = Args(runs_dir=tmp_path, seed=7)
    saved, run_dir = open_run(args, "algo__", lambda path: {"never": "read"})
    assert (
        saved is None
        and run_dir.parent == tmp_path
        and run_dir.name.startswith("algo__TableClearing-IRB120-v1__state__7__")
    )
    first = (random.random(), float(np.random.rand()), float(torch.rand(())))
    open_run(Args(runs_dir=tmp_path, seed=7, exp_name="named"), "algo__", lambda path: {})
    assert first == (random.random(), float(np.random.rand()), float(torch.rand(())))  # seeded alike
    ckpt = tmp_path / "named" / "checkpoints" / "latest.pt"
    saved, run_dir = open_run(Args(resume=ckpt), "algo__", lambda path: {"read": Path(path).name})
    assert saved == {"read": "latest.pt"} and run_dir == (tmp_path / "named").resolve()


def test_a_checkpoint_carries_counters_rng_and_flags_and_restore_continues_the_rng():
    args = Args(seed=3)
    torch.manual_seed(0)
    ckpt = checkpoint("fmt/1", args, dict(wall_s=12.5, env_steps=4), model={"w": 1})
    expected = torch.rand(3)
    torch.manual_seed(99)
    counters = restore(ckpt)
    assert torch.equal(torch.rand(3), expected)
    assert counters == dict(wall_s=12.5, env_steps=4) and counters is not ckpt["counters"]
    assert (ckpt["format"], ckpt["model"], ckpt["args"]["seed"]) == ("fmt/1", {"w": 1}, 3)
    clock = Clock()  # a trainer's clock starts before it reads what it resumes
    restore(ckpt, clock)
    assert 12.5 <= clock() < 17.5


def test_a_resume_of_other_networks_is_refused_naming_what_differs_and_the_flag():
    from types import SimpleNamespace

    from maniskill_irb120.errors import UsageError

    saved = dict(signature=dict(state_dim=3, image=False, logstd="param", obs_norm=True))
    check_resume_signature(saved, dict(saved["signature"]), Path("r/latest.pt"))
    args = SimpleNamespace(logstd="state", obs_norm=False)  # the run's flags: logstd and obs_norm are among them
    ours = dict(state_dim=4, image=False, logstd="state", obs_norm=False)
    with pytest.raises(UsageError) as e:  # one line and exit status 2 from a trainer's command line
        check_resume_signature(saved, ours, Path("r/latest.pt"), args)
    assert str(e.value) == (
        "--resume r/latest.pt: its networks differ from this run's: logstd 'param' in the checkpoint, 'state' in this "
        "run (pass --logstd param); obs_norm True in the checkpoint, False in this run (pass --obs-norm); state_dim 3 "
        "in the checkpoint, 4 in this run"
    )


def test_however_training_ends_the_envs_close_and_the_last_checkpoint_has_the_clock():
    events, saved = [], []

    class Closes:
        def __init__(self, name):
            self.name = name

        def close(self):
            events.append(self.name)

    def save(counters):  # the checkpoint is written before the envs close: their close may be slow
        events.append("saved")
        saved.append(counters)

    counters = dict(env_steps=8, wall_s=0.0)
    try:
        try:
            raise KeyboardInterrupt  # Ctrl-C in the training loop
        finally:
            close_and_save(Closes("bar"), Closes("envs"), counters, Clock(before=30.0), save)
    except KeyboardInterrupt:
        pass
    assert events == ["bar", "saved", "envs"] and saved == [counters] and 30.0 <= counters["wall_s"] < 35
    close_and_save(None, Closes("envs"), counters, Clock(), save)  # no progress bar (--no-progress)
    assert events[-2:] == ["saved", "envs"] and len(saved) == 2


def test_a_failed_save_still_closes_the_envs():
    closed = []

    class Envs:
        def close(self):
            closed.append(True)

    def save(counters):
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        close_and_save(None, Envs(), dict(env_steps=0, wall_s=0.0), Clock(), save)
    assert closed == [True]


def test_closing_envs_interrupted_mid_step_prints_no_gymnasium_warning(recwarn):
    """A Ctrl-C or SIGTERM that lands while the workers step leaves the async vector env waiting on that step; its
    close then finishes the step and shuts the workers without the warning that would precede the one-line message."""
    import gymnasium as gym

    envs = gym.vector.AsyncVectorEnv([lambda: gym.make("CartPole-v1")] * 2)
    envs.reset(seed=0)
    envs.step_async(np.zeros(2, dtype=np.int64))  # the step the interrupt landed in
    close_and_save(None, envs, dict(env_steps=0, wall_s=0.0), Clock(), lambda c: None)
    assert envs.closed and not [w for w in recwarn if "pending call" in str(w.message)]
    with pytest.warns(UserWarning, match="unrelated"):  # only that warning is silenced, not the others
        close_and_save(None, WarnsOnClose(), dict(env_steps=0, wall_s=0.0), Clock(), lambda c: None)


class WarnsOnClose:
    def close(self):
        warnings.warn("unrelated", UserWarning, stacklevel=1)


def test_the_held_out_evaluation_uses_the_runs_task_frame_and_hidden_keys(monkeypatch):
    calls = []
    monkeypatch.setattr(run, "evaluate_on_seeds", lambda *a, **kw: calls.append((a, kw)) or {})
    held_out_evaluation(None, Args(eval_episodes=2, env_kwargs={"reward_mode": "dense"}), control_mode="pd")
    ((args, kw),) = calls
    assert args[1:] == ("TableClearing-IRB120-v1", "state", [10_000_000, 10_000_001])
    assert kw["reward_mode"] == "dense" and kw["control_mode"] == "pd" and "obs_mode" not in kw
    assert [w.__name__ for w in kw["wrappers"]] == ["WorldFrameToolAction"]
    held_out_evaluation(None, HidingArgs(eval_episodes=1), first_seed=5, reward_mode="sparse")
    args, kw = calls[1]
    assert args[3] == [5] and (kw["obs_mode"], kw["reward_mode"]) == ("state_dict", "sparse")
    assert len(kw["wrappers"]) == 2  # the hidden keys' wrapper, then the action frame's


def test_a_resumed_runs_scalars_join_on_the_budget_clock(tmp_path):
    """Two sessions of one run: the second resumed from the checkpoint at step 200, so what the first logged from step
    300 on is dropped; each point sits at the budget clock's minute it was logged at, not at the hours between the
    sessions."""
    from agents.common.logging import Logger, read_scalars

    readings = iter([60.0, 120.0, 180.0, 150.0, 210.0])  # the budget clock's seconds at each scalars() call
    first = Logger(tmp_path, Args(), clock=lambda: next(readings))
    for step, value in ((100, 0.1), (200, 0.2), (300, 0.3)):
        first.scalars({"train/success_rate": value}, step)
    first.close()
    time.sleep(0.05)
    second = Logger(tmp_path, Args(resume=tmp_path / "checkpoints" / "latest.pt"), clock=lambda: next(readings))
    for step, value in ((300, 0.5), (400, 0.6)):
        second.scalars({"train/success_rate": value}, step)
    second.close()
    got = read_scalars(tmp_path)["train/success_rate"]
    assert [s for s, _, _ in got] == [100, 200, 300, 400]
    assert [v for _, _, v in got] == pytest.approx([0.1, 0.2, 0.5, 0.6])  # TensorBoard keeps float32
    assert [m for _, m, _ in got] == pytest.approx([1.0, 2.0, 2.5, 3.5], abs=0.01)


def test_a_run_logged_without_a_clock_continues_each_session_where_the_last_ended(tmp_path):
    """Logs from before the clock was logged (or by another writer): a file's minutes count from its opening, the
    next file's from where the one before it ended."""
    from torch.utils.tensorboard import SummaryWriter

    from agents.common.logging import read_scalars

    for steps in ((100, 200), (300,)):
        with SummaryWriter(tmp_path) as w:
            opened = time.time()  # the writer's first event is at most this late
            for i, step in enumerate(steps):
                w.add_scalar("train/success_rate", step / 1000, step, walltime=opened + 60 * (i + 1))
        time.sleep(0.05)
    got = read_scalars(tmp_path)["train/success_rate"]
    assert [s for s, _, _ in got] == [100, 200, 300]
    assert [m for _, m, _ in got] == pytest.approx([1.0, 2.0, 3.0], abs=0.01)
    assert read_scalars(tmp_path / "nothing") == {}


class FakeClock:
    """The budget clock at whatever second a test sets."""

    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_budget_starts_no_step_that_its_longest_step_and_validation_say_would_end_after_it():
    clock, counters = FakeClock(), {}
    budget = Budget(100.0, clock, counters, validates=True)
    assert budget.next_step_fits()  # nothing measured yet: the first step always starts
    for took, validated in [(10.0, 0.0), (30.0, 5.0), (20.0, 0.0)]:
        budget.start_step()
        clock.now += took - validated
        with budget.validation():
            clock.now += validated
        budget.end_step()
    # steps of 10, 25 (30 less its 5 s validation) and 20 s: the longest step and the longest validation are kept
    assert clock.now == 60.0 and counters["step_s"] == 25.0 and counters["validation_s"] == 5.0
    clock.now = 70.0
    assert budget.next_step_fits()  # 70 + 25 + 5 = 100: ends exactly at the budget
    clock.now = 70.5
    assert not budget.next_step_fits() and not budget.out_of_time()
    clock.now = 95.5
    assert budget.out_of_time()  # within a step: the final validation's 5 s no longer fit
    # the estimates travel in the counters (and so in a checkpoint): a resumed run stops where this one would have
    resumed = Budget(100.0, FakeClock(), dict(counters), validates=True)
    resumed.clock.now = 70.5
    assert not resumed.next_step_fits()
    # a run that validates nothing keeps no time for it; no budget: every step starts
    assert Budget(100.0, resumed.clock, dict(counters), validates=False).next_step_fits()
    clock.now = 1e9
    assert Budget(None, clock, counters, validates=True).next_step_fits()
    assert not Budget(None, clock, counters, validates=True).out_of_time()


def test_the_budget_is_env_steps_counted_on_the_runs_counters_and_the_guard_may_stop_it_early(capsys):
    clock, counters = FakeClock(), dict(global_step=0)
    budget = Budget(60.0, clock, counters, validates=False, total_env_steps=100, steps_key="global_step")
    counters["global_step"] = 99
    assert budget.next_step_fits()  # a step starts while fewer env steps than the budget are done
    counters["global_step"] = 100
    assert not budget.steps_left() and not budget.next_step_fits()
    assert budget.report() == dict(total_env_steps=100, max_minutes=1.0, stopped_early=False)
    # a resumed run's counters carry the env steps it had done: the same budget stops it at the same count
    assert not Budget(None, FakeClock(), dict(counters), False, 100, "global_step").next_step_fits()
    # the guard stops the run first: the summary and the printed line say so
    counters["global_step"], clock.now = 40, 61.0
    assert budget.steps_left() and not budget.next_step_fits() and budget.stopped_early()
    capsys.readouterr()
    assert budget.report()["stopped_early"] is True
    assert capsys.readouterr().out.strip() == "stopped early at 40 env steps (of 100)"
    # no env-step budget: the guard is the budget, and nothing stopped early
    assert Budget(60.0, clock, counters, validates=False).report()["stopped_early"] is False


def test_the_wall_guard_is_max_minutes_else_its_old_name_else_the_trainers_default_without_env_steps():
    from agents.common import wall_guard_s

    assert wall_guard_s(Args(max_minutes=2.0, budget_min=5.0)) == 120.0  # the new flag wins
    assert wall_guard_s(Args(budget_min=5.0)) == 300.0
    assert wall_guard_s(Args(), 60.0) == 3600.0  # no budget at all: the trainer's default minutes
    assert wall_guard_s(Args(total_env_steps=1000), 60.0) is None  # env steps asked for: no clock not asked for
    assert wall_guard_s(Args(total_env_steps=1000, max_minutes=1.0), 60.0) == 60.0


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("total_env_steps", 0, "--total-env-steps must be a positive number of env steps, got 0"),
        ("total_env_steps", -5, "--total-env-steps must be a positive number of env steps, got -5"),
        ("max_minutes", 0.0, "--max-minutes must be a positive number of minutes, got 0.0"),
        ("budget_min", -5.0, "--budget-min must be a positive number of minutes, got -5.0"),
        ("max_minutes", float("nan"), "--max-minutes must be a positive number of minutes, got nan"),
    ],
)
def test_a_zero_or_negative_budget_is_refused_naming_its_flag(field, value, message):
    from agents.common import check_budget

    with pytest.raises(ValueError) as refused:
        check_budget(Args(**{field: value}))
    assert str(refused.value) == message
    check_budget(Args(total_env_steps=1, max_minutes=0.5))  # any positive budget runs
