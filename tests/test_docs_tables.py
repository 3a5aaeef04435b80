"""The docs' generated blocks (``scripts/docs_tables.py``) are what the committed results JSON says now, the
training page lists every committed recipe fastest first with its env-step budget, and the site's nav is the
Diátaxis arrangement that holds every page (``mkdocs build --strict`` itself runs in ``tests/test_docs.py``)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def tables():
    spec = importlib.util.spec_from_file_location("docs_tables", REPO / "scripts" / "docs_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_generated_blocks_are_current():
    """Rerun ``python scripts/docs_tables.py --write`` after a benchmark rewrites its JSON."""
    t = tables()
    for page, names in t.PAGES.items():
        text = (REPO / page).read_text()
        for name in names:
            assert t.begin(name) in text and t.end(name) in text, (page, name)
        assert t.rewrite(page, text) == text, f"{page}: run python scripts/docs_tables.py --write"


def test_a_stale_block_is_caught():
    t = tables()
    text = (REPO / "docs" / "training.md").read_text()
    stale = text.replace(" min | `", " min | `x", 1)
    assert stale != text and t.rewrite("docs/training.md", stale) == text


def test_the_training_table_is_every_committed_recipe_fastest_first():
    """Each row of the committed learning reports once, in the order of its measured minutes, its budget the env steps
    its runs trained (recipes.ENV_STEP_BUDGETS restates them) and its command the recipe's trainer or,
    for a two-stage recipe, the benchmark."""
    import json

    t = tables()
    book = t.recipe_book()
    recipes = book.RECIPES

    page = (REPO / "docs" / "training.md").read_text()
    block = page.split(t.begin("recipes by measured duration"))[1].split(t.end("recipes by measured duration"))[0]
    table = re.findall(r"^\| (\d+) (s|min) \| `([\w-]+)` \| (\w+) \| (\w+) \| ([\d,]+) \| [^|]+ \|$", block, re.M)
    commands = re.findall(r"^(\.venv/bin/python .+?)   # (\d+) (s|min)$", block, re.M)
    assert len(commands) == len(table) and [c[1:] for c in commands] == [r[:2] for r in table]
    rows = [(*row, cmd) for row, (cmd, _, _) in zip(table, commands)]
    seconds = [int(n) * (60 if unit == "min" else 1) for n, unit, *_ in rows]
    assert seconds == sorted(seconds)
    expected = []
    for path in t.LEARNING.values():
        report = json.loads(path.read_text())
        expected += [
            (r["recipe"], report["env_id"].split("-")[0]) for r in report["rows"] if r["recipe"] not in t.REFERENCES
        ]
    assert sorted((name, task) for _, _, name, task, *_ in rows) == sorted(expected)
    for _, _, name, task, obs, steps, cmd in rows:
        assert obs == recipes[name].obs
        env_id = f"{task}-IRB120-v1"
        budget = recipes[name].for_task(env_id).env_steps
        steps = int(steps.replace(",", ""))
        assert f"--total-env-steps {steps}" in cmd
        assert budget is not None and budget[0] == steps, (name, task, steps)
        if recipes[name].base is not None:
            assert f"{t.BENCHMARK}" in cmd and f"--recipes {name}" in cmd
        else:
            assert f"-m {recipes[name].trainer} --recipe {name}" in cmd


def test_the_start_here_path_names_one_first_run_on_every_front_page():
    """README, the docs' home page and the tutorial give the same first training run: the fastest recipe that
    delivers on TableClearing."""
    t = tables()
    first = t.first_run()
    assert first["success"] >= t.DELIVERS and first["task"] == t.FIRST_TASK
    faster = [r for r in t.rows() if r["task"] == t.FIRST_TASK and r["minutes"] < first["minutes"]]
    assert all(r["success"] < t.DELIVERS for r in faster)
    cmd = t.command(first, exp_name="first-run")
    readme = (REPO / "README.md").read_text()
    for text in (readme, (REPO / "docs" / "index.md").read_text(), (REPO / "docs" / "tutorial.md").read_text()):
        assert cmd in text
    # below the README's two commands, before its quickstart
    assert readme.index("## The two commands") < readme.index(cmd) < readme.index("## Quickstart")


def test_no_page_gives_a_budget_in_minutes_by_its_old_name():
    """Budgets are env steps (``--total-env-steps``); minutes only a guard (``--max-minutes``). ``--budget-min`` stays
    in the notes and results, which record how the committed runs were started."""
    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    found = [
        f"{p.name}: {line}" for p in pages for line in p.read_text().splitlines() if re.search(r"--budget-min \d", line)
    ]
    assert found == []


NAV_SECTIONS = ["Home", "Tutorial", "How-to guides", "Reference", "Explanation"]


def nav_pages(nav) -> list[str]:
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += nav_pages(value) if isinstance(value, list) else [value]
    return out


def test_the_nav_is_diataxis_and_holds_every_page():
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    nav = config["nav"]
    assert [next(iter(item)) for item in nav] == NAV_SECTIONS
    pages = nav_pages(nav)
    assert len(pages) == len(set(pages)), "a page twice in the nav"
    generated = {"cli.md", "results.md"}  # scripts/mkdocs_hooks.py makes them at build time
    on_disk = {p.relative_to(REPO / "docs").as_posix() for p in (REPO / "docs").rglob("*.md")}
    assert set(pages) == on_disk | generated
    # and mkdocs itself fails --strict on a page left out of the nav or a nav entry with no page
    assert config["validation"]["nav"] == {"omitted_files": "warn", "not_found": "warn"}
    assert config["strict"] is True
