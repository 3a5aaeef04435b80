"""``benchmarks/`` is a package: each benchmark a thin CLI module run as ``python -m benchmarks.<name>``, over
``benchmarks.lib``. No file of it edits ``sys.path`` and none imports a benchmark CLI module, so what a benchmark
needs from another lives in ``benchmarks.lib``, where every benchmark reads the same code."""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"


def cli_modules(root: Path) -> set[str]:
    """The benchmark CLI modules: ``benchmarks/<name>.py`` but the package's ``__init__``."""
    return {p.stem for p in root.glob("*.py") if p.stem != "__init__"}


def problems(path: Path, clis: set[str], where: str) -> list[str]:
    """``where:line`` and what is wrong, for each ``sys.path`` edit (a call on it, an assignment to it) and each import
    of a benchmark CLI module (``benchmarks.X``, a bare ``X`` as a script's sibling, ``from benchmarks import X``, or
    relatively)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Attribute) and ast.unparse(node) == "sys.path":
            found.append(f"{where}:{node.lineno} uses sys.path")
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = "benchmarks" + ("." + base if base else "") if node.level == 1 and path.parent == BENCH else base
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            sibling = parts[0] in clis and len(parts) == 1
            packaged = parts[0] == "benchmarks" and len(parts) > 1 and parts[1] in clis
            if sibling or packaged:
                found.append(f"{where}:{node.lineno} imports the benchmark {name}")
    return sorted(found, key=lambda hit: (int(hit.split(":")[1].split()[0]), hit))


def test_no_benchmark_edits_sys_path_or_imports_another_benchmark():
    clis = cli_modules(BENCH)
    assert {"learning", "algorithms", "sim_speed"} <= clis
    found = [hit for p in sorted(BENCH.rglob("*.py")) for hit in problems(p, clis, str(p.relative_to(REPO)))]
    assert found == [], "\n".join(found)


def test_the_scan_finds_each_kind(tmp_path):
    bad = tmp_path / "m.py"
    bad.write_text(
        textwrap.dedent(
            """
            import sys
            import learning
            from benchmarks import algorithms
            from benchmarks.learning import run_trainer
            from benchmarks.lib.runner import run_trainer
            sys.path.insert(0, "x")
            sys.path = []
            """
        )
    )
    assert problems(bad, {"learning", "algorithms"}, "m.py") == [
        "m.py:3 imports the benchmark learning",
        "m.py:4 imports the benchmark benchmarks.algorithms",
        "m.py:5 imports the benchmark benchmarks.learning",
        "m.py:5 imports the benchmark benchmarks.learning.run_trainer",
        "m.py:7 uses sys.path",
        "m.py:8 uses sys.path",
    ]
