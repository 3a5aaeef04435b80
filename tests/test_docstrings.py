"""Library docstrings state the rule and its reason; the story of how it came to be, with its dates, lives in
``docs/notes/``. A date (``2026-11-25``) in a docstring of the package, the trainers or the benchmarks fails here,
naming the file and line."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("maniskill_irb120", "agents", "benchmarks")
DATE = re.compile(r"\b(19|20)\d\d-[01]\d-[0-3]\d\b")


def dated_docstring_lines(path: Path, root: Path = REPO) -> list[str]:
    """``path:line: text`` for every docstring line of ``path`` (module, class, function) that holds a date."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) or not node.body:
            continue
        first = node.body[0]
        if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
            for i, line in enumerate(first.value.value.splitlines()):
                if DATE.search(line):
                    found.append(f"{path.relative_to(root)}:{first.lineno + i}: {line.strip()}")
    return found


def test_no_dates_in_library_docstrings():
    found = [hit for root in ROOTS for p in sorted((REPO / root).rglob("*.py")) for hit in dated_docstring_lines(p)]
    assert found == [], "dates belong in docs/notes/, not in docstrings:\n" + "\n".join(found)


def test_the_scan_finds_a_dated_docstring(tmp_path):
    p = tmp_path / "x.py"
    p.write_text(
        '"""A module."""\n\n\ndef f():\n    """The rule.\n\n    Measured on 2026-11-25."""\n    return "2026-11-25"\n'
    )
    assert dated_docstring_lines(p, tmp_path) == ["x.py:7: Measured on 2026-11-25."]
