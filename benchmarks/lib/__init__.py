"""The benchmarks' shared library: running trainers (``runner``, ``adopt``, ``budget``), the statistics (``stats``),
the machine's reference speed (``machine``) and RESULTS.md's sections and plots (``report``). It may import
``agents`` and ``maniskill_irb120``, never a benchmark CLI module (``benchmarks/<name>.py``); those import it."""
