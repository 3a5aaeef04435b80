"""The docs site builds offline with ``mkdocs build --strict`` (every link resolves, the CLI page comes from
``--help``, the API page from the docstrings); the README stays a front page, and its headline table is what
``benchmarks/headline.py`` generates from the committed JSON now; the training page's recipe table and every
``--recipe`` command of the pages agree with ``maniskill_irb120/recipes.py``. (The pages' python blocks run in
``tests/test_readme.py``.)"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
MKDOCS = shutil.which("mkdocs", path=str(Path(sys.executable).parent))


def headline():
    spec = importlib.util.spec_from_file_location("headline", REPO / "benchmarks" / "headline.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_is_a_front_page():
    lines = README.splitlines()
    assert len(lines) <= 150, len(lines)
    assert lines[:4] == [
        "```bash",
        "bash scripts/setup.sh && .venv/bin/python examples/demo.py",
        "bash scripts/setup.sh dev && .venv/bin/python -m pytest",
        "```",
    ]
    heads = [line for line in lines if line.startswith("## ")]
    assert heads == ["## The two commands", "## Quickstart", "## Tasks", "## Headline results", "## Links"], heads


def test_readme_headline_table_is_current():
    """Rerun ``python benchmarks/headline.py --write`` after a benchmark rewrites its JSON."""
    h = headline()
    assert h.block() in README
    assert h.rewrite(README) == README
    # each task's rows in the fixed order, not the report's (its last trained recipe first)
    tc = [line.split("recipe `")[1].split("`")[0] for line in h.learning_rows() if "`TableClearing-IRB120-v1`" in line]
    assert tc == sorted(tc, key=h.ORDER.index) and tc[0].startswith("teacher-student-rgbd")


@pytest.mark.skipif(MKDOCS is None, reason="mkdocs is in the docs and dev extras")
def test_site_builds_strict_offline(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(REPO))
    out = subprocess.run(
        [MKDOCS, "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-5000:]
    site = tmp_path / "site"
    cli = (site / "cli" / "index.html").read_text()
    for command in ("doctor", "expert", "collect-demos", "teleop", "emulator", "sim2real-eval", "sysid", "deploy"):
        assert f"maniskill-irb120 {command}" in cli, command
    assert "make_vec_env" in (site / "api" / "index.html").read_text()
    assert (site / "results" / "index.html").is_file() and (site / "notes" / "index.html").is_file()
    for page in site.rglob("*.html"):  # nothing the site loads comes from the network (fonts, CDN scripts)
        text = page.read_text()
        assert 'src="http' not in text and "fonts.googleapis" not in text, page


def test_the_training_pages_recipe_table_is_the_recipes_module():
    """docs/training.md's table names every recipe of maniskill_irb120/recipes.py once, with its trainer (a
    two-stage recipe: its base's, then its own) and observation."""
    import re

    from maniskill_irb120.recipes import BASES, RECIPES

    page = (REPO / "docs" / "training.md").read_text()
    rows = re.findall(r"^\| `([\w-]+)` \| (.+?) \| (\w+) \|", page, re.M)
    assert sorted(name for name, _, _ in rows) == sorted(RECIPES)
    for name, trainer, obs in rows:
        module = f"`{RECIPES[name].module}`"
        expected = f"`{RECIPES[BASES[name][0]].module}` then {module}" if name in BASES else module
        assert (trainer, obs) == (expected, RECIPES[name].obs), name


def test_every_recipe_command_of_the_docs_parses_on_its_trainer():
    """A ``-m agents.X --recipe NAME ...`` line of the README or a docs page is a command the trainer accepts."""
    import importlib
    import re
    import shlex

    from agents.common import cli

    commands = []
    for page in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = page.read_text().replace("\\\n", " ")
        for module, rest in re.findall(r"-m (agents\.\w+) (--recipe [^\n#`]*)", text):
            commands.append((page.name, module, shlex.split(rest)))
    assert len(commands) >= 8, commands
    for page, module, argv in commands:
        args = cli(importlib.import_module(module).Args, module, argv)
        assert args.recipe == argv[1], (page, argv)
