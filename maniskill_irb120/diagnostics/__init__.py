"""Diagnostics: ``maniskill-irb120 doctor`` (rendering, versions, the GPU acceptance report), the GPU acceptance
checks (``acceptance``) and the runs they make (``acceptance_runs``).

It may import every layer of the package (it checks them all) and no layer imports it; it never imports the
trainers (``agents/``) or the benchmarks: the checks that run them start them as programs in a source checkout
and answer SKIP, with the reason, where the installed package has no checkout beside it.
"""
