"""Diagnostics: ``maniskill-irb120 doctor`` (rendering, versions, the GPU acceptance report), the GPU acceptance
checks (``acceptance``) and the runs they make (``acceptance_runs``).

It may import every layer of the package (it checks them all) and no layer imports it. It never imports the
trainers (``agents/``) or the benchmarks, nor starts them as programs: an installed wheel has neither. The
trainers' and the benchmark's GPU runs are the source checkout's ``benchmarks/gpu_acceptance.py``, which adds
them to the doctor's report (``doctor.gpu_report(programs=...)``).
"""
