"""The one training loop (agents/common/loop.py) on a toy algorithm with no envs: the env-step budget, checkpoint
selection and the held-out evaluation of the selected weights, resume, the checkpoint's format_version and
migrate(), and a removed flag's one-line error."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from agents.common import RunArgs, atomic_save, checkpoint, load_torch, loop
from agents.common.checkpoints import FORMAT_VERSION, migrate

FMT = "toy/1"


@dataclass
class Args(RunArgs):
    steps_per_step: int = 10


class Closed:
    def __init__(self):
        self.closed = False

    def close(self):
        self.closed = True


class Toy(loop.Algorithm):
    """A step adds ``steps_per_step`` env steps and one to ``weight``; a validation scores ``scores[weight]``."""

    name, prefix, step_key = "toy", "toy__", "iteration"

    def __init__(self, args: Args, scores: dict[int, float]):
        super().__init__(args)
        self.counters = dict(env_steps=0, iteration=0)
        self.weight, self.scores, self.evaluated = 0, scores, []
        self.eval_s = 0.0  # seconds each evaluation takes

    def read(self, path: Path) -> dict:
        return load_torch(path, FMT, "the toy")

    def build(self, saved):
        self.envs = Closed()
        if saved is not None:
            self.weight = saved["weight"]
        return self.envs

    def step(self, budget) -> dict:
        self.weight += 1
        self.counters["iteration"] += 1
        self.counters["env_steps"] += self.args.steps_per_step
        return {"train/weight": float(self.weight)}

    def save(self, path: Path, counters: dict) -> None:
        atomic_save(checkpoint(FMT, self.args, counters, weight=self.weight), path)

    def load_selected(self, path: Path) -> None:
        self.weight = self.read(path)["weight"]

    def evaluate(self, args, video_dir=None, first_seed=0) -> dict:
        self.evaluated.append((self.weight, args.eval_episodes))
        time.sleep(self.eval_s)
        rate = self.scores.get(self.weight, 0.0)
        successes = [int(k < rate * args.eval_episodes) for k in range(args.eval_episodes)]
        return {"success_rate": rate, "return": float(self.weight), "successes": successes}

    def summary(self) -> dict:
        return dict(weight=self.weight)


def args(tmp_path: Path, **kw) -> Args:
    return Args(runs_dir=tmp_path, exp_name="t", progress=False, eval_episodes=3, **kw)


def test_the_budget_in_env_steps_ends_training_and_the_summary_says_so(tmp_path):
    toy = Toy(args(tmp_path, total_env_steps=35), {})
    result = loop.run(toy)
    assert result["env_steps"] == 40 and result["weight"] == 4  # a step starts while fewer than 35 are done
    assert result["total_env_steps"] == 35 and result["stopped_early"] is False
    assert toy.envs.closed and toy.evaluated == [(4, 3)]  # the held-out episodes score the last weights
    saved = torch.load(tmp_path / "t" / "checkpoints" / "latest.pt", weights_only=False)
    assert saved["format_version"] == FORMAT_VERSION and saved["counters"]["env_steps"] == 40
    assert json.loads((tmp_path / "t" / "summary.json").read_text())["checkpoint"].endswith("latest.pt")


def test_selection_keeps_the_best_validation_and_the_held_out_episodes_score_it(tmp_path):
    toy = Toy(args(tmp_path, total_env_steps=40, select_episodes=2, select_freq=1), {1: 0.2, 2: 0.9, 3: 0.5})
    result = loop.run(toy)
    assert [w for w, n in toy.evaluated if n == 2] == [1, 2, 3, 4]  # validated after every step
    assert toy.evaluated[-1] == (2, 3)  # the selected weights, not the last (4)
    assert result["selected"] == dict(
        iteration=2, env_steps=20, validation_success_rate=0.9, validation_episodes=2
    ) and result["checkpoint"].endswith("best.pt")
    assert result["last_checkpoint"].endswith("latest.pt")
    # every check is in the summary, [env steps, success rate, mean return], and a resume carries them on
    assert result["selection_checks"] == [[10, 0.2, 1.0], [20, 0.9, 2.0], [30, 0.5, 3.0], [40, 0.0, 4.0]]
    latest = tmp_path / "t" / "checkpoints" / "latest.pt"
    again = loop.run(Toy(args(tmp_path, total_env_steps=50, select_episodes=2, select_freq=1, resume=latest), {}))
    assert again["selection_checks"] == [*result["selection_checks"], [50, 0.0, 5.0]]


def test_resume_continues_the_counters_and_the_weights(tmp_path):
    first = Toy(args(tmp_path, total_env_steps=20), {})
    loop.run(first)
    latest = tmp_path / "t" / "checkpoints" / "latest.pt"
    again = Toy(args(tmp_path, total_env_steps=50, resume=latest), {})
    result = loop.run(again)
    assert result["env_steps"] == 50 and result["weight"] == 5


def test_held_out_curve_points_come_at_shares_of_the_budget_off_the_clock_and_go_on_after_a_resume(tmp_path):
    """--curve-points: the policy as it is on --curve-episodes held-out seeds once the env steps cross each share
    (a quarter, a half, three quarters for 4), the end left to the final evaluation; their time is not training."""
    toy = Toy(args(tmp_path, total_env_steps=50, curve_points=4, curve_episodes=2), {2: 1.0, 4: 0.5})
    toy.eval_s = 0.2
    result = loop.run(toy)
    rows = result["held_out_curve"]
    # shares 12.5, 25 and 37.5 of 50, crossed by the steps that end at 20, 30 and 40 env steps
    assert [r[0] for r in rows] == [20, 30, 40] and [r[2] for r in rows] == [1.0, 0.0, 0.5]
    assert [r[3] for r in rows] == [[1, 1], [0, 0], [1, 0]] and all(r[4] >= 0.2 for r in rows)
    assert toy.evaluated == [(2, 2), (3, 2), (4, 2), (5, 3)]  # the points, then the final evaluation's 3 episodes
    assert result["wall_clock_s"] < 0.2  # three 0.2 s evaluations, none of them on the budget clock
    latest = tmp_path / "t" / "checkpoints" / "latest.pt"
    again = Toy(args(tmp_path, total_env_steps=100, curve_points=4, curve_episodes=2, resume=latest), {})
    rows = loop.run(again)["held_out_curve"]
    # the points so far are kept; the next share past the last (40) is 50 of 100, crossed at 60, then 75 at 80
    assert [r[0] for r in rows] == [20, 30, 40, 60, 80]


def test_a_step_that_crosses_several_shares_takes_one_point(tmp_path):
    toy = Toy(args(tmp_path, total_env_steps=100, curve_points=4, curve_episodes=1, steps_per_step=60), {})
    result = loop.run(toy)
    assert [r[0] for r in result["held_out_curve"]] == [60]  # 25 and 50 at once; 75 falls in the last step


@pytest.mark.parametrize(
    "kw, says",
    [
        (dict(curve_points=-1, total_env_steps=10), "--curve-points must be >= 0"),
        (dict(curve_points=4, curve_episodes=0, total_env_steps=10), "--curve-episodes >= 1"),
        (dict(curve_points=4), "give --total-env-steps"),
    ],
)
def test_a_curve_that_cannot_be_taken_is_refused_by_name(kw, says):
    from agents.common.args import check_budget

    with pytest.raises(ValueError, match=says):
        check_budget(Args(**kw))


def test_migrate_brings_a_version_1_ppo_checkpoint_up_to_date():
    old = dict(
        format="maniskill_irb120.ppo/1",
        signature=dict(image_shape=None, state_dim=3, action_dim=5),
        counters=dict(global_step=16, iteration=1, best=dict(score=[1.0, 2.0], iteration=1, global_step=16)),
        args=dict(total_env_steps=None, total_timesteps=20_000, max_wall_s=90.0, budget_min=None, partial_reset=True),
    )
    new = migrate(old)
    assert new["args"]["total_env_steps"] == 20_000 and new["args"]["max_minutes"] == 1.5
    assert "total_timesteps" not in new["args"] and "partial_reset" not in new["args"]
    assert new["format_version"] == FORMAT_VERSION and new["args"]["action_frame"] == "tool"
    assert new["counters"]["env_steps"] == 16 and "global_step" not in new["counters"]
    assert new["counters"]["best"]["env_steps"] == 16
    assert new["signature"]["residual"] is False and new["signature"]["logstd"] == "param"
    with pytest.raises(ValueError, match="newer than this code's"):
        migrate(dict(format="x", format_version=FORMAT_VERSION + 1))


@pytest.mark.parametrize(
    "module, argv, says",
    [
        ("agents.ppo", ["--total-timesteps", "5"], "--total-timesteps was removed; use --total-env-steps"),
        ("agents.ppo", ["--max-wall-s=60"], "--max-wall-s was removed; use --max-minutes (in minutes)"),
        (
            "agents.sac",
            ["--no-partial-reset"],
            "--no-partial-reset was removed; training always auto-resets",
        ),
        ("agents.dagger", ["--evaluate", "runs/x/latest.pt"], "--evaluate takes no value; name the checkpoint with"),
    ],
)
def test_a_removed_flag_is_one_line_naming_its_successor_and_exit_status_2(module, argv, says, refused):
    refused(module, argv, says)


def test_ctrl_c_in_a_run_is_one_line_and_exit_130_and_a_missing_extra_names_its_setup(capsys):
    """A Ctrl-C reaches the trainer's entry after the loop saved latest.pt (its finally): one line saying how to
    continue, exit 130, no traceback. A trainer run on the plain setup, without the rl extras, is told the command
    that installs them, exit 2; a missing module that is no extra keeps its traceback."""
    from agents import ppo
    from agents.common import entry

    def interrupted(args):
        raise KeyboardInterrupt

    def no_tensorboard(args):
        raise ModuleNotFoundError("No module named 'tensorboard'", name="tensorboard")

    def no_such_module(args):
        raise ModuleNotFoundError("No module named 'nothing_here'", name="nothing_here")

    with pytest.raises(SystemExit) as stop:
        entry(ppo.Args, "agents.ppo", interrupted, ["--total-env-steps", "8"])
    err = capsys.readouterr().err
    assert stop.value.code == 130 and err.count("\n") == 1 and "--resume" in err
    with pytest.raises(SystemExit) as stop:
        entry(ppo.Args, "agents.ppo", no_tensorboard, ["--total-env-steps", "8"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and "bash scripts/setup.sh rl" in err
    with pytest.raises(ModuleNotFoundError):
        entry(ppo.Args, "agents.ppo", no_such_module, ["--total-env-steps", "8"])
