"""``--recipe NAME`` on each trainer: the recipe's flags for the task, the command line's over them, and a clear
refusal of a name the trainer cannot run (another trainer's, an unknown one, a two-stage one)."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from agents.common import cli, recipe_argv
from agents.recipes import RECIPES

REPO = Path(__file__).resolve().parents[2]


def parsed(module: str, argv: list[str]):
    return cli(importlib.import_module(module).Args, module, argv)


@pytest.mark.parametrize("name", [r for r in RECIPES if RECIPES[r].base is None])
def test_every_single_stage_recipe_parses_on_its_trainer_as_its_flags_do(name):
    module = RECIPES[name].trainer
    by_name = parsed(module, ["--recipe", name, "--seed", "2"])
    resolved = RECIPES[name].for_task("TableClearing-IRB120-v1")
    budget = [] if resolved.env_steps is None else ["--total-env-steps", str(resolved.env_steps[0])]
    by_hand = parsed(module, [*resolved.argv(2), *budget, "--seed", "2"])
    assert by_name.recipe == name and by_name.obs == RECIPES[name].obs
    assert {**vars(by_name), "recipe": None} == {**vars(by_hand), "recipe": None}


def test_a_recipe_takes_its_tasks_own_flags_and_the_runs_seed():
    grasp = parsed("agents.ppo", ["--recipe", "ppo-state", "--env-id", "GraspLift-IRB120-v1"])
    clear = parsed("agents.ppo", ["--recipe=ppo-state"])
    assert RECIPES["ppo-state"].tasks["GraspLift-IRB120-v1"].flags == {"logstd": "state"}
    assert (grasp.logstd, clear.logstd) == ("state", "param")
    assert (grasp.state_net, grasp.obs_norm, grasp.num_steps, grasp.select_episodes) == ("mlp", True, 128, 30)
    dr = parsed("agents.dagger", ["--recipe", "dagger-rgbd-bf16-dr", "--seed", "3"])
    assert str(dr.init_policy).endswith("dagger-rgbd-bf16-s3-60min.pt")
    assert dr.env_kwargs["reconfiguration_freq"] == 5


def test_explicit_flags_override_the_recipes():
    args = parsed("agents.dagger", ["--recipe", "dagger-rgbd", "--batch-size", "32", "--obs-without", "state"])
    assert (args.batch_size, args.updates_per_round, args.encoder) == (32, 500, "keypoints")
    assert tuple(args.obs_without) == ("state",)
    assert recipe_argv("agents.sac", ["--seed", "4"], "TableClearing-IRB120-v1", 1) == ["--seed", "4"]


def test_a_name_the_trainer_cannot_run_is_refused_with_the_valid_names():
    ppo_names = "ppo-rgbd, ppo-rgbd-dense, ppo-rgbd-dense-fast, ppo-rgbd-fast, ppo-state"
    with pytest.raises(
        ValueError, match=f"a recipe of agents.dagger, not of agents.ppo; agents.ppo's recipes: {ppo_names}$"
    ):
        parsed("agents.ppo", ["--recipe", "dagger-state"])
    with pytest.raises(ValueError, match="'nope': no such recipe; agents.sac's recipes: sac-scratch-state, sac-state$"):
        parsed("agents.sac", ["--recipe", "nope"])
    with pytest.raises(ValueError, match=r"ppo-finetune-state: a two-stage recipe \(a dagger-state run first, its "):
        parsed("agents.ppo", ["--recipe", "ppo-finetune-state"])
    with pytest.raises(ValueError, match="python -m benchmarks.learning --recipes teacher-student-rgbd"):
        parsed("agents.dagger", ["--recipe", "teacher-student-rgbd"])


def test_the_trainers_command_line_expands_a_recipe(monkeypatch):
    # sys.argv, read in this process (a fresh interpreter's imports took half a minute on a loaded CI box; the
    # command line of a `python -m` trainer is test_python_m_a_trainer_with_a_negative_budget_exits_2_with_one_line's)
    from agents.sac import Args

    monkeypatch.setattr(sys, "argv", ["agents.sac", "--recipe", "sac-scratch-state", "--batch-size", "64"])
    a = cli(Args, "agents.sac")
    assert (a.recipe, a.demo_episodes, a.eval_deterministic, a.batch_size) == ("sac-scratch-state", 0, False, 64)


@pytest.mark.parametrize("module", ["agents.ppo", "agents.dagger", "agents.sac"])
def test_resume_alone_continues_with_the_runs_own_flags_and_a_flag_given_again_overrides(tmp_path, module):
    """``--resume CKPT`` without the flags the run was started with: each is read back from the checkpoint (a path,
    a tuple, a float given as an int), not left at the trainer's default; a flag on the command line wins."""
    from agents.common.checkpoints import atomic_save
    from agents.common.run import checkpoint

    trainer = importlib.import_module(module)
    started = parsed(module, ["--env-id", "GraspLift-IRB120-v1", "--seed", "3", "--budget-min", "56", "--obs", "state"])
    started.runs_dir, started.exp_name = tmp_path / "runs", "cut"
    if hasattr(started, "obs_without"):
        started.obs_without = ("agent/qvel",)
    ckpt = tmp_path / "latest.pt"
    atomic_save(checkpoint(trainer.FORMAT, started, dict(wall_s=60.0)), ckpt)
    resumed = parsed(module, ["--resume", str(ckpt)])
    assert {**vars(resumed), "resume": None} == vars(started) and resumed.resume == ckpt
    assert isinstance(resumed.runs_dir, Path) and isinstance(resumed.budget_min, float)
    longer = parsed(module, ["--resume", str(ckpt), "--budget-min", "90"])
    assert longer.budget_min == 90.0 and longer.env_id == "GraspLift-IRB120-v1" and longer.seed == 3
    with pytest.raises(FileNotFoundError, match="--resume: checkpoint .*missing.pt does not exist"):
        parsed(module, ["--resume", str(tmp_path / "missing.pt")])
    atomic_save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt: the file holds no run arguments"):
        parsed(module, ["--resume", str(tmp_path / "other.pt")])


def test_resuming_a_recipe_run_with_env_kwargs_takes_the_recipes_again_or_keeps_the_runs(tmp_path):
    """A run started with --env-kwargs (teacher-student-rgbd-sel-dr's randomisation) resumes with its recipe named
    again, as the docs' command does; tyro would read the resumed dict as fixed --env-kwargs.KEY options and refuse
    the recipe's --env-kwargs KEY VALUE. Without the flag the run's own env kwargs are kept; given, they win."""
    from agents import dagger
    from agents.common.checkpoints import atomic_save
    from agents.common.run import checkpoint

    recipe = ["--recipe", "teacher-student-rgbd-sel-dr", "--seed", "1"]
    started = parsed("agents.dagger", recipe)
    assert "camera_fov" in started.env_kwargs["randomization"]
    started.runs_dir, started.exp_name = tmp_path / "runs", "dr"
    ckpt = tmp_path / "latest.pt"
    atomic_save(checkpoint(dagger.FORMAT, started, dict(wall_s=60.0)), ckpt)
    again = parsed("agents.dagger", [*recipe, "--resume", str(ckpt), "--total-env-steps", "91226"])
    assert again.env_kwargs == started.env_kwargs and again.total_env_steps == 91226 and again.exp_name == "dr"
    assert parsed("agents.dagger", ["--resume", str(ckpt)]).env_kwargs == started.env_kwargs
    other = parsed("agents.dagger", ["--resume", str(ckpt), "--env-kwargs", "randomization", "light=0.3:1.6"])
    assert other.env_kwargs == {"randomization": "light=0.3:1.6"}


@pytest.mark.parametrize("module", ["agents.ppo", "agents.dagger", "agents.sac"])
@pytest.mark.parametrize(
    "argv, says",
    [
        (["--budget-min", "-5"], "--budget-min must be a positive number of minutes, got -5.0"),
        (["--total-env-steps", "0"], "--total-env-steps must be a positive number of env steps, got 0"),
        (["--max-minutes", "0"], "--max-minutes must be a positive number of minutes, got 0.0"),
        (["--total-env-steps", "abc"], "Error parsing --total-env-steps: "),
    ],
)
def test_a_command_line_with_no_budget_is_refused_in_one_line_with_exit_status_2(module, argv, says, refused):
    """A zero or negative budget would train nothing, write a checkpoint and exit 0; it ends before any env with one
    line naming the flag (no traceback, no tyro panel) and exit status 2."""
    refused(module, argv, says)


def test_python_m_a_trainer_with_a_negative_budget_exits_2_with_one_line():
    argv = [sys.executable, "-m", "agents.ppo", "--budget-min", "-5"]
    out = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr == "agents.ppo: error: --budget-min must be a positive number of minutes, got -5.0\n"


def test_the_rllib_trainer_refuses_a_budget_in_one_line_too(capsys):
    from agents.common import entry
    from agents.rllib.train import Args

    ran = []
    for argv, says in [
        (["--timesteps", "0"], "--timesteps was removed; use --total-env-steps"),
        (["--total-env-steps", "-3"], "--total-env-steps must be a positive number of env steps, got -3"),
        (["--budget-min", "-5"], "--budget-min must be a positive number of minutes, got -5.0"),
    ]:
        with pytest.raises(SystemExit) as stop:
            entry(Args, "agents.rllib", ran.append, argv, recipes=False)
        assert stop.value.code == 2 and capsys.readouterr().err == f"agents.rllib: error: {says}\n"
    assert not ran
