"""Solve N seeded K = 8 measurements with one solver (for instruction counts).

Timings on a shared machine drift with its load; instruction counts do not. Run it under
callgrind twice, with 0 and with 10 solves, and divide the difference by 10::

    valgrind --tool=callgrind --callgrind-out-file=/dev/null python -m bench.solve_loop 0
    valgrind --tool=callgrind --callgrind-out-file=/dev/null python -m bench.solve_loop 10

(paper room, correlation, 30 dB; one warm-up solve in both runs, after the compiled kernels'
warm-up). ``--kernels reference`` runs the plain NumPy kernels instead of the compiled ones;
``--model`` and ``--targets`` pick another measurement model and K.
"""

from __future__ import annotations

import argparse

import numpy as np

from app.vlp._kernels import KERNELS, use_kernels
from app.vlp.fingerprints import build_fingerprint
from app.vlp.measurements import Model, measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers import make_solver, warm_up

N_TARGETS = 8


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.solve_loop``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("solves", type=int, help="how many measurements to solve")
    parser.add_argument("--solver", default="gridless")
    parser.add_argument("--model", default="correlation", choices=("correlation", "power"))
    parser.add_argument("--targets", type=int, default=N_TARGETS, help="K (default 8)")
    parser.add_argument("--kernels", default="compiled", choices=KERNELS)
    args = parser.parse_args(argv)
    with use_kernels(args.kernels):
        warm_up()
        _solve_all(args.solver, args.model, args.targets, args.solves)
    return 0


def _solve_all(name: str, model: Model, n_targets: int, solves: int) -> None:
    layout = paper_layout()
    fingerprint = build_fingerprint(layout)
    solver = make_solver(name, fingerprint, model)
    sigma = noise_std_for_snr(fingerprint, 30.0)
    measurements = []
    for seed in range(max(solves, 1)):
        rng = np.random.default_rng(5000 + seed)
        truth = random_positions(layout, n_targets, rng=rng)
        amplitudes = noisy_amplitudes(layout, truth, sigma, rng=rng)
        measurements.append(measurement_from_amplitudes(amplitudes, model, layout.n_leds))
    solver.solve(measurements[0], n_targets)  # warm-up, in both runs
    for measurement in measurements[:solves]:
        solver.solve(measurement, n_targets)


if __name__ == "__main__":
    raise SystemExit(main())
