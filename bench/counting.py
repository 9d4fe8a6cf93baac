"""Counting with K unknown (``targets`` left out) when every amplitude is off by one factor.

A survey from another day, a receiver whose gain drifted, pilots driven a little harder: the
measurement is the fingerprint's times a common amplitude scale ``s`` (``R`` times ``s^2``).
With K given, the default solver fits that scale; with K unknown it must also count. This
draws, per condition, scale and K, fixed-seed placements at 30 dB (the ideal model, the
realistic mix with the reflectance in the layout, or terminal gains with sd 10 %) times
``common_scale=s`` and reports how often the default solver's count is right, which counts it
gave, and the mean matched error of the right counts.

    python -m bench.counting                               # paper room, K = 4, 20 placements
    python -m bench.counting --rooms paper,hall --ks 2,4 --trials 30 --conditions ideal,mix
    python -m bench.counting --out docs        # writes docs/results/counting.md

Prints a markdown table; with ``--out DIR`` also writes it between the ``counting`` markers
of ``DIR/results/counting.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.simulation import Impairments
from app.vlp.solvers.gridless import GridlessSolver

from ._common import measured_section, replace_section
from ._real_rooms_extra import draw_terminals
from .real_rooms import MIX, _fingerprint, _generator, _layout

__all__ = ["CountCell", "count_cell", "main"]

SCALES = (0.83, 0.9, 0.95, 1.0, 1.05, 1.1, 1.17)
SNR_DB = 30.0


@dataclass(frozen=True)
class CountCell:
    """One cell: the fraction of right counts, the counts given (count -> placements) and
    the mean matched error of the right counts (metres; NaN when none was right)."""

    right: float
    counts: dict[int, int]
    error: float


CONDITIONS = {
    "ideal": Impairments.ideal(),
    "mix": MIX,
    "gains": Impairments.gain_spread(0.10),
}


def count_cell(
    room: str, count: int, scale: float, trials: int, condition: str = "ideal"
) -> CountCell:
    """Count ``count`` targets ``trials`` times under a common amplitude ``scale`` and one
    of :data:`CONDITIONS` (``mix``: the realistic mix, reflectance in the layout)."""
    reflectance = MIX.reflectance if condition == "mix" else None
    layout = _layout(room, reflectance)
    solver = GridlessSolver(_fingerprint(room, reflectance), "correlation")
    impairments = dataclasses.replace(CONDITIONS[condition], common_scale=scale)
    given: list[int] = []
    errors: list[float] = []
    for trial in range(trials):
        # The placements and the noise do not depend on the scale: the rows are paired.
        truth, simulated = draw_terminals(
            layout,
            count,
            impairments,
            snr_db=SNR_DB,
            placement_rng=_generator("counting", room, count, trial),
            noise_rng=_generator("counting-noise", room, condition, count, trial),
        )
        measurement = measurement_from_amplitudes(
            simulated.amplitudes, "correlation", layout.n_leds
        )
        solution = solver.solve(measurement, None)
        given.append(solution.n_targets)
        if solution.n_targets == count:
            errors.append(mean_position_error(solution.positions, truth))
    right = sum(1 for value in given if value == count) / trials
    error = float(np.mean(errors)) if errors else float("nan")
    return CountCell(right, dict(sorted(Counter(given).items())), error)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.counting``."""
    parser = argparse.ArgumentParser(prog="python -m bench.counting", description=__doc__)
    parser.add_argument("--rooms", default="paper", help="comma-separated rooms")
    parser.add_argument("--ks", default="4", help="comma-separated target counts")
    parser.add_argument("--scales", default=",".join(map(str, SCALES)), help="amplitude scales")
    parser.add_argument("--trials", type=int, default=20, help="placements per cell")
    parser.add_argument(
        "--conditions", default="ideal", help=f"comma-separated, of {', '.join(CONDITIONS)}"
    )
    parser.add_argument("--out", type=Path, default=None, help="write DIR/results/counting.md")
    args = parser.parse_args(argv)
    rooms = [room.strip() for room in args.rooms.split(",") if room.strip()]
    counts = [int(k) for k in args.ks.split(",")]
    scales = [float(s) for s in args.scales.split(",")]
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = sorted(set(conditions) - set(CONDITIONS))
    if unknown:
        parser.error(f"unknown conditions {unknown}; choose from {sorted(CONDITIONS)}")
    started = time.perf_counter()
    lines = [
        "| room | condition | K | amplitude scale | right count | counts given (count: placements) "
        "| mean error of the right counts (cm) |",
        "|---|---|---|---|---|---|---|",
    ]
    with threadpool_limits(limits=1):
        for room, condition, count, scale in itertools.product(rooms, conditions, counts, scales):
            cell = count_cell(room, count, scale, args.trials, condition)
            given = ", ".join(f"{k}: {n}" for k, n in cell.counts.items())
            error = "-" if np.isnan(cell.error) else f"{100 * cell.error:.1f}"
            lines.append(
                f"| {room} | {condition} | {count} | {scale:g} | {cell.right:.2f} | {given} "
                f"| {error} |"
            )
            print(lines[-1], flush=True)
    elapsed = time.perf_counter() - started
    if args.out is not None:
        command = "python -m bench.counting " + " ".join(argv if argv is not None else sys.argv[1:])
        body = measured_section(
            "## Counting under a common amplitude scale (`bench/counting.py`)",
            f"Command: `{command.strip()}` ({elapsed:.0f} s), {SNR_DB:g} dB, the "
            f"condition times one amplitude scale, {args.trials} placements per cell, "
            "`targets` left out, default solver (`mix`: the realistic mix with the "
            "reflectance in the layout; `gains`: terminal gains sd 10 %).",
            "\n".join(lines),
        )
        replace_section(
            args.out / "results" / "counting.md",
            "counting",
            body,
            preamble="# Results: counting the terminals\n",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
