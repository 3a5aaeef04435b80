"""Shared by the benchmark tests.

``bench_script``: ``bench_script(name)`` is the module ``benchmarks.<name>``, executed afresh on every call, so a test
that replaces one of its functions leaves the next test's copy alone (``benchmarks.lib`` is shared: patch it with
monkeypatch, which undoes it).
The test modules cannot import a helper (``--import-mode=importlib``), so the loader is handed to them as a fixture.

``gpu_trainer``: a test asking for it runs once per trainer that ``benchmarks/gpu_acceptance.py`` checks (its
``TRAINERS``, read when the tests are collected).
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

import pytest


def load_bench_script(name: str) -> ModuleType:
    """The module ``benchmarks.<name>``, executed afresh."""
    spec = importlib.util.find_spec(f"benchmarks.{name}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while the file executes
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def bench_script():
    """``load(name)``: ``benchmarks.<name>`` as a freshly executed module."""
    return load_bench_script


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "gpu_trainer" in metafunc.fixturenames:
        metafunc.parametrize("gpu_trainer", load_bench_script("gpu_acceptance").TRAINERS)
