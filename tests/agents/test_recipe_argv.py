"""Each typed recipe renders the command line its list form did before recipes became data: the same flags and
values in the same order, on every task, with the same base, share, budget kind and env-step budget. The expected
lists (``data/recipe_argv.json``) were written from the list-form module, ``maniskill_irb120/recipes.py`` of the
commit before ``agents/recipes.py``; a recipe changed on purpose changes them with it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agents.recipes import RECIPES, Recipe, TaskChange, recipe, render

PINNED = json.loads((Path(__file__).parent / "data" / "recipe_argv.json").read_text())


def test_the_pinned_recipes_are_the_recipes():
    assert list(PINNED) == list(RECIPES)


@pytest.mark.parametrize("name", list(PINNED))
def test_a_recipe_renders_its_list_forms_command_on_every_task(name):
    pinned = PINNED[name]
    base = RECIPES[name].base
    assert ([base.recipe, base.share, f"--{base.hand_on}"] if base else None) == pinned["base"]
    for task, want in pinned["tasks"].items():
        r = recipe(name, task)
        assert r.argv(3) == want["argv"], task
        assert (r.trainer, r.obs, r.budget) == (pinned["trainer"], pinned["obs"], pinned["budget"])
        assert (r.base.share if r.base else None) == want["base_share"], task
        assert (list(r.env_steps) if r.env_steps else None) == want["env_steps"], task
        assert r.minutes(task) == want["minutes"], task


def test_a_task_change_is_data_and_leaves_the_recipe_as_it_was():
    ppo = RECIPES["ppo-state"]
    grasp = ppo.for_task("GraspLift-IRB120-v1")
    assert grasp.flags["logstd"] == "state" and "logstd" not in ppo.flags and ppo.task is None
    assert grasp.argv()[-2:] == ["--logstd", "state"]
    sel = RECIPES["teacher-student-rgbd-sel"]
    assert (sel.for_task("TableClearing-IRB120-v1").base.share, sel.base.share) == (0.6, 0.375)
    with pytest.raises(AttributeError):
        ppo.trainer = "agents.sac"  # frozen


def test_render_writes_each_kind_of_value():
    flags = {"obs-norm": True, "reference": False, "gamma": 0.8, "n": 4, "path": "s{seed}.pt", "kw": ("a", "1")}
    assert render(flags, 7) == ["--obs-norm", "--no-reference", "--gamma", "0.8", "--n", "4", "--path", "s7.pt"] + [
        "--kw",
        "a",
        "1",
    ]
    change = Recipe("x", "agents.ppo", "state", "rl", {"n": 1}, tasks={"T": TaskChange(flags={"n": 2})})
    assert change.for_task("T").argv() == ["--n", "2"] and change.for_task("U").argv() == ["--n", "1"]
