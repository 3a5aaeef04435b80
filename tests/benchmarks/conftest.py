"""Shared by the benchmark tests.

``bench_script``: ``bench_script(name)`` is ``benchmarks/<name>.py`` as a module, executed afresh on every call (the
scripts are programs, not a package), so a test that replaces one of its functions leaves the next test's copy alone.
The test modules cannot import a helper (``--import-mode=importlib``), so the loader is handed to them as a fixture.

``gpu_trainer``: a test asking for it runs once per trainer that ``benchmarks/gpu_acceptance.py`` checks (its
``TRAINERS``, read when the tests are collected).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def load_bench_script(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` as the module ``name``, with benchmarks/ on sys.path while it executes (sim_speed
    imports its sibling pybullet_original)."""
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up while the file executes
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH))
    return mod


@pytest.fixture(scope="session")
def bench_script():
    """``load(name)``: ``benchmarks/<name>.py`` as a freshly executed module."""
    return load_bench_script


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "gpu_trainer" in metafunc.fixturenames:
        metafunc.parametrize("gpu_trainer", load_bench_script("gpu_acceptance").TRAINERS)
