"""The benchmarks, each a thin CLI module run from the repository root as ``python -m benchmarks.<name>``, over the
shared library in ``benchmarks.lib``. A benchmark module imports ``benchmarks.lib``, ``agents`` and
``maniskill_irb120``, never another benchmark module, and edits no ``sys.path`` (tests/test_benchmark_package.py)."""
