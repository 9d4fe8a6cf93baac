"""Power solves in a large room with local refinements against full ones, in-process.

The ``gridless`` solver refines, after each insertion or relocation in a large room, only
the targets near the change (``gridless.fitting.lm_fit_near``); switched off (its reach set to
None) it refines all of them, as in small rooms. For each seed: K random terminals at
``--snr`` dB (the API's ``/simulate`` draws: positions, then noisy amplitudes), the power
measurement solved both ways; reported per way: misplaced targets (error above 0.5 m), the
median and worst of the per-seed mean errors and the per-seed solve time (median, max).

    python -m bench.hall_refinement [--room hall|medium] [--targets 50] [--seeds 1-20]

``hall``: the million-point hall of :mod:`bench.hall_build`; ``medium``: 40 x 40 m, 0.1 m
grid, 144 LEDs on a 3.2 m pitch (the room of ``tests/vlp/gridless/test_local.py``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from typing import Any

import numpy as np

from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.measurements import Measurement, measurement_from_amplitudes
from app.vlp.metrics import matched_errors
from app.vlp.rng import as_generator
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.typing import FloatArray
from bench._common import machine_record
from bench.hall_build import million_point_hall

__all__ = ["main", "medium_hall", "run"]

# A target farther than this from every truth counts as misplaced, metres.
_MISPLACED_M = 0.5


def medium_hall() -> Layout:
    """40 x 40 m, 0.1 m grid (N = 160 000), 144 LEDs on a 3.2 m pitch at 3 m, FOV 70."""
    leds = tuple(
        Led(x=3.2 * (i + 0.5), y=3.2 * (j + 0.5), z=3.0) for i in range(12) for j in range(12)
    )
    return Layout(
        Room(40.0, 40.0, 3.0), Grid(0.1, 0.85), leds, Receiver(fov_deg=70.0), name="medium"
    )


def _problems(
    layout: Layout, noise_std: float, targets: int, seeds: range
) -> list[tuple[FloatArray, Measurement]]:
    problems = []
    for seed in seeds:
        rng = as_generator(seed)
        truth = random_positions(layout, targets, rng=rng)
        amplitudes = noisy_amplitudes(layout, truth, noise_std, rng=rng)
        problems.append((truth, measurement_from_amplitudes(amplitudes, "power", layout.n_leds)))
    return problems


def run(room: str, targets: int, seeds: range, snr_db: float) -> dict[str, Any]:
    """Solve every seed both ways; the figures of each way."""
    layout = million_point_hall() if room == "hall" else medium_hall()
    fingerprint = build_fingerprint(layout)
    solver = GridlessSolver(fingerprint, "power")
    reach = solver.room.near_reach
    if reach is None:
        raise SystemExit(f"the {room} room is not large by the solver's rule")
    problems = _problems(layout, noise_std_for_snr(fingerprint, snr_db), targets, seeds)
    solver.solve(problems[0][1], targets)  # compile or load the kernels first
    report: dict[str, Any] = {"room": room, "targets": targets, "snr_db": snr_db}
    report["seeds"] = f"{seeds.start}-{seeds.stop - 1}"
    for way, way_reach in (("local", reach), ("full", None)):
        solver.room.near_reach = way_reach
        misplaced, means, times = 0, [], []
        for truth, measurement in problems:
            started = time.perf_counter()
            solution = solver.solve(measurement, targets)
            times.append(time.perf_counter() - started)
            errors = matched_errors(solution.positions, truth)
            misplaced += int(np.sum(errors > _MISPLACED_M))
            means.append(float(np.mean(errors)))
        report[way] = {
            "misplaced": f"{misplaced} of {targets * len(problems)}",
            "median_mean_error_cm": round(100 * statistics.median(means), 2),
            "worst_mean_error_cm": round(100 * max(means), 2),
            "median_solve_s": round(statistics.median(times), 3),
            "max_solve_s": round(max(times), 3),
        }
    solver.room.near_reach = reach
    report["machine"] = machine_record()
    return report


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.hall_refinement``."""
    parser = argparse.ArgumentParser(prog="python -m bench.hall_refinement")
    parser.add_argument("--room", choices=("hall", "medium"), default="hall")
    parser.add_argument("--targets", type=int, default=50)
    parser.add_argument("--seeds", default="1-20", help="first-last, inclusive")
    parser.add_argument("--snr", type=float, default=30.0)
    args = parser.parse_args(argv)
    first, _, last = str(args.seeds).partition("-")
    seeds = range(int(first), int(last or first) + 1)
    print(json.dumps(run(args.room, args.targets, seeds, args.snr), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
