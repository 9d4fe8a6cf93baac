"""Solve N seeded K = 8 measurements with one solver (for instruction counts).

Timings on a shared machine drift with its load; instruction counts do not. Run it under
callgrind twice, with 0 and with 10 solves, and divide the difference by 10::

    valgrind --tool=callgrind --callgrind-out-file=/dev/null python -m bench.solve_loop 0
    valgrind --tool=callgrind --callgrind-out-file=/dev/null python -m bench.solve_loop 10

(paper room, correlation, 30 dB; one warm-up solve in both runs).
"""

from __future__ import annotations

import argparse

import numpy as np

from app.vlp.fingerprints import build_fingerprint
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers import make_solver

N_TARGETS = 8


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.solve_loop``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("solves", type=int, help="how many measurements to solve")
    parser.add_argument("--solver", default="gridless")
    args = parser.parse_args(argv)
    layout = paper_layout()
    fingerprint = build_fingerprint(layout)
    solver = make_solver(args.solver, fingerprint, "correlation")
    sigma = noise_std_for_snr(fingerprint, 30.0)
    measurements = []
    for seed in range(max(args.solves, 1)):
        rng = np.random.default_rng(5000 + seed)
        truth = random_positions(layout, N_TARGETS, rng=rng)
        amplitudes = noisy_amplitudes(layout, truth, sigma, rng=rng)
        measurements.append(measurement_from_amplitudes(amplitudes, "correlation", layout.n_leds))
    solver.solve(measurements[0], N_TARGETS)  # warm-up, in both runs
    for measurement in measurements[: args.solves]:
        solver.solve(measurement, N_TARGETS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
