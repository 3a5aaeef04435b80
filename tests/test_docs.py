"""The docs site builds offline with ``mkdocs build --strict`` (every link resolves, the CLI page comes from
``--help``, the API page from the docstrings); the README stays a front page, and its headline table is what
``benchmarks/headline.py`` generates from the committed JSON now; the training page's recipe table and every
``--recipe`` command of the pages agree with ``agents/recipes.py``. (The pages' python blocks run in
``tests/test_readme.py``.)

What ``--strict`` does not catch is checked here too: a line that Python-Markdown makes a heading though it was
never meant as one (a wrapped link whose next line starts with ``#1003](...)``: a page-wide H1 that drops the
sections after it from the table of contents), and, on the built site, every section of a page in its table of
contents."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
MKDOCS = shutil.which("mkdocs", path=str(Path(sys.executable).parent))


def headline():
    return importlib.import_module("benchmarks.headline")


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
    sections = ["The two commands", "Start here", "Quickstart", "Tasks", "Headline results", "Links"]
    assert heads == [f"## {name}" for name in sections], heads


def test_readme_headline_table_is_current():
    """Rerun ``python benchmarks/headline.py --write`` after a benchmark rewrites its JSON."""
    h = headline()
    assert h.block() in README
    assert h.rewrite(README) == README
    # each task's rows in the fixed order, not the report's (its last trained recipe first)
    tc = [line.split("recipe `")[1].split("`")[0] for line in h.learning_rows() if "`TableClearing-IRB120-v1`" in line]
    assert tc == sorted(tc, key=h.ORDER.index) and tc[0].startswith("teacher-student-rgbd")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``mkdocs build --strict`` once for the module: (its exit status and output, the site folder)."""
    if MKDOCS is None:
        pytest.skip("mkdocs is in the docs and dev extras")
    site = tmp_path_factory.mktemp("docs") / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(REPO))
    out = subprocess.run(
        [MKDOCS, "build", "--strict", "--site-dir", str(site)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return out, site


def test_site_builds_strict_offline(built):
    out, site = built
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-5000:]
    cli = (site / "cli" / "index.html").read_text()
    for command in ("doctor", "expert", "collect-demos", "teleop", "emulator", "sim2real-eval", "sysid", "deploy"):
        assert f"maniskill-irb120 {command}" in cli, command
    assert "make_vec_env" in (site / "api" / "index.html").read_text()
    assert (site / "stylesheets" / "extra.css").is_file() and "stylesheets/extra.css" in cli  # mkdocs.yml's extra_css
    assert (site / "results" / "index.html").is_file() and (site / "notes" / "index.html").is_file()
    # the results page's link to benchmarks/results/ (a folder: no page on the site) goes to its list of the files
    results = (site / "results" / "index.html").read_text()
    assert 'href="./#files"' in results and 'id="files"' in results and 'href="sim_speed.json"' in results
    for page in site.rglob("*.html"):  # nothing the site loads comes from the network (fonts, CDN scripts)
        text = page.read_text()
        assert 'src="http' not in text and "fonts.googleapis" not in text, page


PAGES = [REPO / "README.md", REPO / "benchmarks" / "RESULTS.md", *sorted((REPO / "docs").rglob("*.md"))]
FENCE = re.compile(r"^\s*(```|~~~)")


def stray_headings(text: str) -> list[str]:
    """``line N: why: text`` for each line outside fenced code that Python-Markdown reads as a heading though it
    was not written as one: ``#`` then no space (Python-Markdown needs none: ``#1003](https://...)``, a wrapped
    link's second line, is an H1), or a heading straight after a line of text (a wrapped sentence's next line
    that starts with ``# ``)."""
    found, fence, prev = [], None, ""
    for n, line in enumerate(text.splitlines(), 1):
        opens = FENCE.match(line)
        if fence:
            fence = None if opens and line.strip().startswith(fence) else fence
            prev = ""
            continue
        if opens:
            fence, prev = opens.group(1), ""
            continue
        if line.startswith("#"):
            if not re.match(r"#{1,6} \S", line):
                found.append(f"line {n}: '#' without a space after it is a heading all the same: {line}")
            elif prev.strip() and not prev.lstrip().startswith(("#", "<!--")):
                found.append(f"line {n}: a heading in the middle of a paragraph: {line}")
        prev = line
    return found


def test_no_line_is_a_heading_by_accident():
    found = [f"{p.relative_to(REPO)} {hit}" for p in PAGES for hit in stray_headings(p.read_text())]
    assert found == [], "rewrap so no line starts with '#':\n" + "\n".join(found)


def test_the_heading_scan_finds_a_wrapped_link_and_a_wrapped_heading():
    text = (
        "# Title\n\n## A section\n\nSee [issue\n#1003](https://x/1003) for it.\nA sentence that ends\n# here\n\n"
        "```bash\n# a comment\n#!shebang\n```\n<!-- note -->\n## After a comment\n"
    )
    assert stray_headings(text) == [
        "line 6: '#' without a space after it is a heading all the same: #1003](https://x/1003) for it.",
        "line 8: a heading in the middle of a paragraph: # here",
    ]


def fence_errors(text: str) -> list[str]:
    """``line N: why: text`` for each fence Markdown does not close where it was meant to: a closing fence with text
    after it (CommonMark and Python-Markdown read it as code, so the block runs on through the prose after it), and
    a block still open at the end of the page."""
    found, fence, start = [], None, 0
    for n, line in enumerate(text.splitlines(), 1):
        opens = FENCE.match(line)
        if fence is None:
            if opens:
                fence, start = opens.group(1), n
        elif opens and line.strip().startswith(fence):
            if line.strip().strip(fence[0]):
                found.append(f"line {n}: text after a closing fence leaves the block open: {line}")
            fence = None
    if fence is not None:
        found.append(f"line {start}: a fence never closed")
    return found


def test_every_fenced_block_closes_on_a_bare_fence():
    found = [f"{p.relative_to(REPO)} {hit}" for p in PAGES for hit in fence_errors(p.read_text())]
    assert found == [], "end each block on a line of the fence alone:\n" + "\n".join(found)
    text = "Run:\n\n```bash\nls\n``` then it lists.\n\n```\nopen\n"
    assert fence_errors(text) == [
        "line 5: text after a closing fence leaves the block open: ``` then it lists.",
        "line 7: a fence never closed",
    ]


def test_every_section_of_a_page_is_in_its_table_of_contents(built):
    """Each ``<h2>`` of a built page has its entry in the page's table of contents (Material drops the sections
    after a second H1 from it), and the page has one H1."""
    out, site = built
    assert out.returncode == 0, out.stderr[-3000:]
    bad = []
    for page in sorted(site.rglob("index.html")):
        html = page.read_text()
        if "md-sidebar--secondary" not in html:
            continue
        start, content = html.index("md-sidebar--secondary"), html.index('class="md-content"')
        toc, body = html[start:content], html[content:]
        missing = [h for h in re.findall(r'<h2 id="([^"]+)"', body) if f'href="#{h}"' not in toc]
        h1 = len(re.findall(r"<h1[ >]", body))
        if missing or h1 != 1:
            bad.append(f"{page.relative_to(site)}: {h1} H1, sections not in the table of contents: {missing}")
    # and each page written by hand has as many sections as its source has ## headings (mkdocstrings' pages add
    # their own)
    for src in sorted((REPO / "docs").rglob("*.md")):
        text = src.read_text()
        if "\n::: " in text:
            continue
        rel = src.relative_to(REPO / "docs").with_suffix("")
        page = site / (rel.parent if rel.name == "index" else rel) / "index.html"
        heads, fence = 0, False
        for line in text.splitlines():
            fence ^= bool(FENCE.match(line))
            heads += not fence and line.startswith("## ")
        built = len(re.findall(r"<h2 id=", page.read_text()))
        if built != heads:
            bad.append(f"{src.relative_to(REPO)}: {heads} ## headings, {built} sections on the site")
    assert bad == [], "\n".join(bad)


def test_the_training_pages_recipe_table_is_the_recipes_module():
    """docs/training.md's table names every recipe of agents/recipes.py once, with its trainer (a
    two-stage recipe: its base's, then its own) and observation."""
    import re

    from agents.recipes import RECIPES

    page = (REPO / "docs" / "training.md").read_text()
    rows = re.findall(r"^\| `([\w-]+)` \| (.+?) \| (\w+) \|", page, re.M)
    assert sorted(name for name, _, _ in rows) == sorted(RECIPES)
    for name, trainer, obs in rows:
        module, base = f"`{RECIPES[name].trainer}`", RECIPES[name].base
        expected = f"`{RECIPES[base.recipe].trainer}` then {module}" if base else module
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
