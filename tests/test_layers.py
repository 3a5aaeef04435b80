"""The layout's rules, read from the code's own imports (each folder's ``__init__`` states its rule in words).

Imports point one way: ``action`` < ``robot/`` < ``envs/`` < ``vector``/``wrappers`` < ``experts/`` <
``policies/`` < ``sim2real/``; ``abb/`` beside them (its wire side: no ManiSkill, no SAPIEN; a robot PC needs
neither); ``teleop/`` over ``experts/`` and ``abb/`` (its devices and jogging: no ManiSkill, no SAPIEN either).
Imports inside functions count as much as module-level ones: a lazy import is still a dependency.

Nor does the package run what it does not ship: no module of it starts a program other than the few system tools
allowed below (with the reason), and what it runs in a fresh interpreter is its own code. The trainers
(``agents/``), the benchmarks and ``scripts/`` are a source checkout's, which an installed wheel does not have;
the checks that run them are ``benchmarks/gpu_acceptance.py``'s.
"""

from __future__ import annotations

import ast
import re
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
    "diagnostics/ never imports the trainers or the benchmarks (a wheel has neither)": (
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


# --------------------------------------------------------------------------- no import cycles
def import_time_imports(path: Path, root: Path) -> set[str]:
    """The modules of ``root``'s package that ``path`` imports while it is being imported: module level and class
    bodies, ``if TYPE_CHECKING:`` blocks included; not imports inside functions. ``from pkg import name`` is
    ``pkg.name`` where that is a module, else ``pkg``."""
    here = ".".join(path.relative_to(root).with_suffix("").parts)
    package = here.rsplit(".", 1)[0] if path.name != "__init__.py" else here.removesuffix(".__init__")

    def is_module(name: str) -> bool:
        f = root.joinpath(*name.split("."))
        return f.with_suffix(".py").is_file() or (f / "__init__.py").is_file()

    out: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, ast.Import):
                out.update(a.name for a in child.names if is_module(a.name))
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                for a in child.names:
                    if is_module(f"{base}.{a.name}"):
                        out.add(f"{base}.{a.name}")
                    elif is_module(base):
                        out.add(base)
            visit(child)

    visit(ast.parse(path.read_text()))
    return out


def import_cycles(root: Path, package: str) -> list[list[str]]:
    """Each set of ``package``'s modules that import one another round (strongly connected, more than one)."""
    paths = sorted((root / package).rglob("*.py"))
    names = [".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__") for p in paths]
    graph = {n: import_time_imports(p, root) - {n} for n, p in zip(names, paths)}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            connect(v)
    return cycles


def test_no_import_cycles():
    """No two modules of the package import each other, directly or round a longer loop. What counts is what runs
    when a module is imported, and ``if TYPE_CHECKING:`` imports too (a type checker follows them, and an
    annotation that needs the importer is a dependency all the same: the emulator's two cycles were of that kind).
    Imports inside functions do not count here: they run once every module is initialised (``open_device``
    importing the driver it was asked for, ``vector``'s worker importing the package); the layer rules above
    still see them."""
    assert import_cycles(PKG.parent, PKG.name) == []


def test_the_cycle_scan_counts_type_checking_imports_and_not_those_in_functions(tmp_path):
    pkg = tmp_path / "p"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from p.b import B\n")
    (pkg / "b.py").write_text("from . import a\n\nclass B:\n    from p import c\n")
    (pkg / "c.py").write_text("def load():\n    from p import b\n")
    assert import_cycles(tmp_path, "p") == [["p.a", "p.b"]]
    (pkg / "a.py").write_text("def f():\n    from p.b import B\n")
    assert import_cycles(tmp_path, "p") == []


# --------------------------------------------------------------------------- programs the package starts
STARTERS = {
    "subprocess": {"run", "call", "check_call", "check_output", "Popen", "getoutput", "getstatusoutput"},
    "os": {"system", "popen", "startfile", "posix_spawn", "posix_spawnp"}
    | {f"exec{s}" for s in ("l", "le", "lp", "lpe", "v", "ve", "vp", "vpe")}
    | {f"spawn{s}" for s in ("l", "le", "lp", "lpe", "v", "ve", "vp", "vpe")},
    "asyncio": {"create_subprocess_exec", "create_subprocess_shell"},
    "pty": {"spawn"},
}
"""every standard-library call that starts a program, by module"""
ALLOWED_PROGRAMS = {
    ("maniskill_irb120/diagnostics/doctor.py", "nvidia-smi"): "the NVIDIA driver's version for the GPU report "
    "(torch knows only the CUDA it was built with); a system tool, not a file of the checkout",
}
"""(module, program) -> why the package may start it"""


def program_starts(path: Path, root: Path) -> list[str]:
    """``file:line starts PROGRAM`` for each call in ``path`` that starts a program (``subprocess``, ``os.system``,
    ``os.exec*``/``spawn*``, ``asyncio``'s and ``pty``'s, under any alias), PROGRAM the command's first word when
    it is written out, else ``<a command built at run time>``; and ``file:line runs MODULE in a fresh
    interpreter`` for each ``isolated(MODULE, ...)`` (acceptance_runs), MODULE resolved through a name assigned
    a string in the same file."""
    tree = ast.parse(path.read_text())
    where = path.relative_to(root).as_posix()
    modules: dict[str, str] = {}  # alias -> module (import subprocess as sp)
    functions: dict[str, tuple[str, str]] = {}  # alias -> (module, function) (from subprocess import run)
    strings: dict[str, str] = {}  # name -> the string constant assigned to it
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update({a.asname or a.name: a.name for a in node.names if a.name in STARTERS})
        elif isinstance(node, ast.ImportFrom) and node.module in STARTERS:
            functions.update({a.asname or a.name: (node.module, a.name) for a in node.names})
        elif (
            isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)
        ):
            strings.update({t.id: node.value.value for t in node.targets if isinstance(t, ast.Name)})

    def text(arg: ast.AST | None) -> str | None:
        if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
            return arg.value
        if isinstance(arg, ast.Attribute) and ast.unparse(arg) == "sys.executable":
            return "python"
        return strings.get(arg.id) if isinstance(arg, ast.Name) else None

    def first_arg(call: ast.Call) -> ast.AST | None:
        return call.args[0] if call.args else next((k.value for k in call.keywords if k.arg in ("args", "cmd")), None)

    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id in modules:
            target = (modules[f.value.id], f.attr)
        elif isinstance(f, ast.Name) and f.id in functions:
            target = functions[f.id]
        else:
            target = None
        if target is not None and target[1] in STARTERS[target[0]]:
            cmd = first_arg(node)
            word = text(cmd.elts[0]) if isinstance(cmd, (ast.List, ast.Tuple)) and cmd.elts else text(cmd)
            program = word.split()[0] if word and word.split() else "<a command built at run time>"
            found.append(f"{where}:{node.lineno} starts {program}")
        elif (f.id if isinstance(f, ast.Name) else getattr(f, "attr", None)) == "isolated":
            found.append(f"{where}:{node.lineno} runs {text(first_arg(node))} in a fresh interpreter")
    return found


def test_the_package_starts_no_program_of_a_checkout():
    found = [hit for p in sorted(PKG.rglob("*.py")) for hit in program_starts(p, PKG.parent)]
    allowed = {f"{module} starts {program}" for module, program in ALLOWED_PROGRAMS}
    bad = [
        hit
        for hit in found
        if not (" runs maniskill_irb120." in hit or re.sub(r":\d+ starts", " starts", hit) in allowed)
    ]
    assert bad == [], (
        "the package may start only the programs ALLOWED_PROGRAMS names and run only its own modules in a fresh "
        "interpreter (agents/, benchmarks/, scripts/ are a checkout's: benchmarks/gpu_acceptance.py runs them):\n"
        + "\n".join(bad)
    )
    stale = allowed - {re.sub(r":\d+ starts", " starts", hit) for hit in found}
    assert not stale, f"ALLOWED_PROGRAMS names programs the package no longer starts: {sorted(stale)}"


def test_the_program_scan_finds_each_way_to_start_one(tmp_path):
    p = tmp_path / "m.py"
    p.write_text(
        textwrap.dedent(
            """
            import os, subprocess as sp, sys
            from subprocess import Popen as P
            from maniskill_irb120.diagnostics.acceptance_runs import isolated

            MOD = "agents.ppo"
            sp.run([sys.executable, "-m", "agents.ppo"])
            P(["python", "benchmarks/sim_speed.py"])
            os.system("bash scripts/setup.sh")
            os.execvp("nvidia-smi", ["nvidia-smi"])
            cmd = ["x"]
            sp.check_output(args=cmd)
            isolated(MOD, "main")
            isolated("maniskill_irb120.diagnostics.acceptance_runs", "run_named_check")
            print("subprocess.run")
            """
        )
    )
    assert program_starts(p, tmp_path) == [
        "m.py:7 starts python",
        "m.py:8 starts python",
        "m.py:9 starts bash",
        "m.py:10 starts nvidia-smi",
        "m.py:12 starts <a command built at run time>",
        "m.py:13 runs agents.ppo in a fresh interpreter",
        "m.py:14 runs maniskill_irb120.diagnostics.acceptance_runs in a fresh interpreter",
    ]


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
