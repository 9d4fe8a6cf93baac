"""Benchmarks (not collected by pytest): localization accuracy and in-process solver timing.

- ``python -m bench.accuracy [--quick] [--out docs]``: the paper's Fig. 3 and Fig. 4 and a
  harder room, written to ``docs/results/accuracy.md``, ``docs/data/*.csv`` and
  ``docs/figures/*.png``.
- ``python -m bench.solver_timing [--out docs]``: median/p90 solve time per solver and model,
  written to ``docs/results/solver-timing.md``.

Every benchmark and its results page: ``docs/how-to/reproduce-the-results.md``.
"""
