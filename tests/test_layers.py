"""The layout's rules, read from the code's own imports (each folder's ``__init__`` states its rule in words).

Imports point one way: ``action`` < ``robot/`` < ``envs/`` < ``vector``/``wrappers`` < ``experts/`` <
``policies/`` < ``sim2real/``; ``abb/`` beside them (its wire side: no ManiSkill, no SAPIEN; a robot PC needs
neither); ``teleop/`` over ``experts/`` and ``abb/`` (its devices and jogging: no ManiSkill, no SAPIEN either).
Imports inside functions count as much as module-level ones: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "maniskill_irb120"


def imports_of(path: Path) -> set[str]:
    """Every module name ``path`` imports (absolute; relative imports resolved), at any depth."""
    tree = ast.parse(path.read_text())
    here = ".".join(path.relative_to(PKG.parent).with_suffix("").parts)
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = here.split(".")[: -node.level]
                base = ".".join(parts + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def files(folder: str) -> list[Path]:
    root = PKG / folder
    return sorted(root.rglob("*.py")) if root.is_dir() else [root.with_suffix(".py")]


def offenders(paths: list[Path], forbidden: tuple[str, ...]) -> list[str]:
    bad = []
    for p in paths:
        for name in imports_of(p):
            if any(name == f or name.startswith(f + ".") for f in forbidden):
                bad.append(f"{p.relative_to(PKG.parent)} imports {name}")
    return bad


M = "maniskill_irb120"
WIRE = [p for p in files("abb") if "emulator" not in p.parts]

RULES = {
    "action.py uses numpy and torch only": (
        files("action"),
        ("mani_skill", "sapien", "gymnasium", M + ".robot", M + ".envs", M + ".abb", M + ".sim2real", "agents"),
    ),
    "the wire side never imports ManiSkill, SAPIEN or the sim layers": (
        WIRE,
        ("mani_skill", "sapien", M + ".envs", M + ".experts", M + ".sim2real", M + ".robot.irb120")
        + (M + ".robot.controllers", M + ".robot.shaders", M + ".vector", M + ".wrappers", "agents"),
    ),
    "robot/ never imports envs/ or anything above": (
        files("robot"),
        (M + ".envs", M + ".experts", M + ".sim2real", M + ".abb", M + ".vector", M + ".wrappers", "agents"),
    ),
    "robot's kinematics and description run without ManiSkill (the wire side uses them)": (
        files("robot/kinematics") + files("robot/description"),
        ("mani_skill", "sapien"),
    ),
    "envs/ never imports sim2real/, abb/, experts/ or agents/": (
        files("envs"),
        (M + ".sim2real", M + ".abb", M + ".experts", M + ".vector", M + ".wrappers", "agents"),
    ),
    "experts/ never imports sim2real/, abb/ or agents/": (
        files("experts"),
        (M + ".sim2real", M + ".abb", "agents"),
    ),
    "the emulator never imports envs/, experts/ or sim2real/": (
        files("abb/emulator"),
        (M + ".envs", M + ".experts", M + ".sim2real", "agents"),
    ),
    "policies/ (what a deployed policy runs) needs torch only": (
        files("policies"),
        ("mani_skill", "sapien", "gymnasium", M + ".envs", M + ".experts", M + ".sim2real", M + ".abb", "agents"),
    ),
    "teleop/ never imports sim2real/ or agents/": (
        files("teleop"),
        (M + ".sim2real", "agents"),
    ),
    "teleop's devices and jogging run on a robot PC: no ManiSkill, no SAPIEN, no sim layers": (
        [p for p in files("teleop") if p.stem in ("devices", "keyboard", "spacemouse", "gamepad", "jog")],
        ("mani_skill", "sapien", "gymnasium", M + ".envs", M + ".experts", M + ".abb.emulator")
        + (M + ".robot.irb120", M + ".robot.controllers", M + ".vector", M + ".wrappers"),
    ),
    "the library never imports the trainers": (sorted(PKG.rglob("*.py")), ("agents",)),
    "no layer imports integrations/ (the adapters to other RL libraries sit on top)": (
        [p for p in sorted(PKG.rglob("*.py")) if "integrations" not in p.parts],
        (M + ".integrations",),
    ),
    "integrations/ never imports the trainers or the benchmarks": (files("integrations"), ("agents", "benchmarks")),
    "diagnostics/ never imports the trainers or the benchmarks (it runs them as programs, in a checkout)": (
        files("diagnostics"),
        ("agents", "benchmarks"),
    ),
    "no layer imports diagnostics/ (it checks the layers; the CLI starts it)": (
        [p for p in sorted(PKG.rglob("*.py")) if "diagnostics" not in p.parts and p.name != "cli.py"],
        (M + ".diagnostics",),
    ),
}


@pytest.mark.parametrize("rule", list(RULES))
def test_imports_point_one_way(rule):
    paths, forbidden = RULES[rule]
    assert paths, rule
    assert offenders(paths, forbidden) == [], rule


def test_every_folder_says_what_it_may_import():
    for init in PKG.rglob("__init__.py"):
        if "rapid" in init.parts:
            continue
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        assert "import" in doc, f"{init.relative_to(PKG.parent)} has no docstring saying what it may import"


def test_wire_side_runs_without_maniskill_or_sapien():
    """A robot PC's interpreter: ManiSkill and SAPIEN cannot be imported at all, and the client still connects
    its envelope and encodes a frame (and the teleop devices and jogger import)."""
    code = textwrap.dedent(
        """
        import importlib.abc, sys

        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name.split(".")[0] in ("mani_skill", "sapien"):
                    raise ModuleNotFoundError(f"No module named {name!r}", name=name)

        sys.meta_path.insert(0, Block())
        from maniskill_irb120.abb import client, deploy, envelope, protocol
        from maniskill_irb120.teleop import devices, gamepad, jog, keyboard, spacemouse
        env = envelope.Envelope()
        import numpy as np
        q = env.check_tool_step(np.radians([0, 19.05, 26.51, 0, 44.44, 0]), [0.0, 0.0, 0.005], 0.0)
        frame = protocol.command_frame(protocol.ToolStep(0.0, 0.0, 0.005, 0.0, True), 1).encode()
        assert "mani_skill" not in sys.modules and "sapien" not in sys.modules
        print(len(frame), q.shape)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["15", "(6,)"]
