"""Benchmarks (not collected by pytest): localization accuracy and in-process solver timing.

- ``python -m bench.accuracy [--quick] [--out docs]``: the paper's Fig. 3 and Fig. 4 and a
  harder room, written to ``docs/accuracy.md``, ``docs/data/*.csv`` and ``docs/figures/*.png``.
- ``python -m bench.solver_timing [--out docs]``: median/p90 solve time per solver and model,
  written to the "Solver timings" section of ``docs/performance.md``.
"""
