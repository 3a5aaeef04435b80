"""The layers hold by import: a trainer in agents/ imports agents.common and the library, never another trainer;
the library (maniskill_irb120/) never imports agents; sim2real's policy loader does not edit sys.path."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TRAINERS = ("agents.ppo", "agents.sac", "agents.dagger", "agents.rllib")


def imported(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; ``from agents import dagger`` counts as agents.dagger)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            raise AssertionError(f"{path}: relative import (the layer test reads absolute names)")
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "__import__":
            out.add("<__import__>")
    return out


def trainer_of(path: Path) -> str | None:
    rel = path.relative_to(REPO).with_suffix("")
    name = ".".join(rel.parts)
    return next((t for t in TRAINERS if name == t or name.startswith(t + ".")), None)


def under(name: str, pkg: str) -> bool:
    return name == pkg or name.startswith(pkg + ".")


AGENT_FILES = sorted((REPO / "agents").rglob("*.py"))
LIBRARY_FILES = sorted((REPO / "maniskill_irb120").rglob("*.py"))


@pytest.mark.parametrize("path", AGENT_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_no_trainer_imports_another(path):
    own = trainer_of(path)
    bad = sorted(n for n in imported(path) for t in TRAINERS if under(n, t) and t != own)
    assert not bad, f"{path.relative_to(REPO)} imports another trainer: {bad}"


@pytest.mark.parametrize("path", sorted((REPO / "agents" / "common").rglob("*.py")), ids=lambda p: p.name)
def test_common_imports_no_trainer(path):
    bad = sorted(n for n in imported(path) for t in TRAINERS if under(n, t))
    assert not bad, f"{path.relative_to(REPO)} imports a trainer: {bad}"


def test_the_library_never_imports_agents():
    bad = {str(p.relative_to(REPO)): sorted(n for n in imported(p) if under(n, "agents")) for p in LIBRARY_FILES}
    assert not {k: v for k, v in bad.items() if v}


def test_policies_import_only_torch_numpy_and_the_action_space():
    # maniskill_irb120.errors: the standard library only (checked below), so a policy still needs torch alone
    allowed = ("torch", "numpy", "__future__", "collections", "copy", "hashlib", "typing", "pathlib",
               "maniskill_irb120.action", "maniskill_irb120.errors")  # fmt: skip
    assert not [n for n in imported(REPO / "maniskill_irb120" / "errors.py") if under(n, "maniskill_irb120")]
    for p in sorted((REPO / "maniskill_irb120" / "policies").glob("*.py")):
        bad = [
            n
            for n in imported(p)
            if not any(under(n, a) for a in allowed) and not under(n, "maniskill_irb120.policies")
        ]
        assert not bad, f"{p.relative_to(REPO)} imports {bad}"


def test_the_policy_loader_leaves_sys_path_alone():
    path = REPO / "maniskill_irb120" / "sim2real" / "policy.py"
    tree = ast.parse(path.read_text())
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    attrs = {
        f"{n.value.id}.{n.attr}"
        for n in ast.walk(tree)
        if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
    }
    assert "sys" not in names and "sys.path" not in attrs
    assert not any(under(n, "sys") or under(n, "agents") for n in imported(path)) and "<__import__>" not in imported(
        path
    )
