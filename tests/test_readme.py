"""Every python block of README.md and of the docs pages (``docs/*.md``) runs as written, in a fresh interpreter
(blocks with a marker naming another test are run, with more checks, there; blocks marked slow, which train, run
with ``-m slow``)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
MARKER = (
    r"(<!-- (?:README )?snippet \"[^\"]+\" \(run [^)]*?tests/([\w/]+)\.py(, slow[^)]*)?\) -->\s*)?```python\n(.*?)```"
)
BLOCKS = [
    (page.relative_to(REPO).as_posix(), test, bool(slow), code)
    for page in PAGES
    for _, test, slow, code in re.findall(MARKER, page.read_text(), re.S)
]
FRAGMENTS: dict[str, str] = {}  # page -> why its block cannot run as written (none today: every block runs)
OURS = [(page, slow, code) for page, test, slow, code in BLOCKS if test in ("", "test_readme")]


def test_every_block_is_run_somewhere():
    others = {test for _, test, _, _ in BLOCKS if test not in ("", "test_readme")}
    for test in others:
        assert (Path(__file__).parent / f"{test}.py").exists(), test
    assert len([1 for page, _, _ in OURS if page == "README.md"]) >= 1
    assert len(OURS) >= 2


@pytest.mark.parametrize(
    "page, code",
    [
        pytest.param(
            page,
            code,
            marks=([pytest.mark.slow] if slow else [])
            + ([pytest.mark.skip(reason=FRAGMENTS[page])] if page in FRAGMENTS else []),
        )
        for page, slow, code in OURS
    ],
    ids=[f"{page}:{code.splitlines()[0][:40]}" for page, _, code in OURS],
)
def test_block_runs(page, code, tmp_path):
    script = tmp_path / "snippet.py"
    script.write_text(code)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, f"{page}: " + out.stderr[-3000:]
