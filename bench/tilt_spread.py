"""What a tilt spread declared in the layout does to the ``terminals`` form.

With ``grid.receiver_tilt_sd`` in the layout, the default solver fits each terminal's
photodiode tilt with that spread as its prior (a terminal that sends no ``normal``). This
solves the same K = 8 terminals (30 dB, fixed seeds, the draws of ``bench/real_rooms.py``'s
row of the same name) with the layout as given and with the spread declared, and reports
per case the mean error, how often the truth falls inside ``accuracy_m`` and the median
radius, and the paired difference of the mean errors (declared minus not, with its standard
error over the placements). The declared spread is the condition's own tilts'
(:attr:`Impairments.tilt_component_sd_deg`), or the realistic mix's in a room whose
photodiodes are level (a spread declared that the terminals do not have).

    python -m bench.tilt_spread                   # writes docs/results/tilt-spread.md
    python -m bench.tilt_spread --trials 5 --rooms paper --out bench/out/quick
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.calibration import calibrate, calibrated_layout
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Layout
from app.vlp.radii import confidence_radii
from app.vlp.simulation import TRUE_ELEMENT_SIZE_M
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.survey import simulate_survey
from app.vlp.typing import FloatArray

from ._common import REPO_ROOT, machine_markdown, machine_record, replace_section
from ._real_rooms_extra import _survey_points, draw_terminals
from .real_rooms import CONDITIONS, MIX, Condition, _generator, _layout

__all__ = ["CASES", "Case", "Outcome", "main", "run_case"]

COUNT = 8
SNR_DB = 30.0


@dataclass(frozen=True)
class Case:
    """A row: the main benchmark's condition, and whether a survey calibrates the layout."""

    condition: str
    calibrated: bool = False

    @property
    def name(self) -> str:
        return self.condition + (", after a survey calibration" if self.calibrated else "")


CASES: tuple[Case, ...] = (
    Case("ideal"),
    Case("LED 5 % / 3 deg"),
    Case("tilt 0-20 deg"),
    Case("realistic mix, reflectance in layout"),
    Case("realistic mix, reflectance and height sd in layout"),
    Case("realistic mix, reflectance in layout", calibrated=True),
)


@dataclass(frozen=True)
class Outcome:
    """Per terminal: errors (m) and 95 % radii (m), the layout as given and declared."""

    errors: dict[str, FloatArray]
    radii: dict[str, FloatArray]


def _with_tilt_sd(layout: Layout, tilt_sd_deg: float) -> Layout:
    grid = dataclasses.replace(layout.grid, receiver_tilt_sd=tilt_sd_deg)
    return dataclasses.replace(layout, grid=grid)


def run_case(room: str, case: Case, trials: int) -> Outcome:
    """Solve every placement of ``case`` with the layout as given and with the spread."""
    condition: Condition = next(c for c in CONDITIONS if c.name == case.condition)
    impairments = condition.impairments
    spread = impairments.tilt_component_sd_deg or MIX.tilt_component_sd_deg
    layout = _layout(room, condition.reflectance_in_layout, condition.height_sd_in_layout)
    errors: dict[str, list[FloatArray]] = {"as given": [], "declared": []}
    radii: dict[str, list[FloatArray]] = {"as given": [], "declared": []}
    solvers: dict[str, GridlessSolver] = {}
    for trial in range(trials):
        positions, simulated = draw_terminals(
            layout,
            COUNT,
            impairments,
            snr_db=SNR_DB,
            placement_rng=_generator(room, COUNT, trial),
            noise_rng=_generator(room, condition.name, COUNT, trial),
        )
        told = layout
        if case.calibrated:
            survey = simulate_survey(
                simulated.true_layout,
                _survey_points(layout),
                simulated.noise_std,
                rng=_generator(room, "survey", trial),
                element_size_m=TRUE_ELEMENT_SIZE_M,
            )
            told = calibrated_layout(layout, calibrate(layout, survey))
            solvers.clear()
        for name, tilt_sd in (("as given", told.grid.receiver_tilt_sd), ("declared", spread)):
            if name not in solvers:
                fingerprint = build_fingerprint(_with_tilt_sd(told, tilt_sd))
                solvers[name] = GridlessSolver(fingerprint, "correlation")
            solution = solvers[name].solve_terminals(simulated.amplitudes)
            assert solution.covariances is not None
            errors[name].append(np.linalg.norm(solution.positions - positions, axis=1))
            radii[name].append(confidence_radii(solution.covariances))
    return Outcome(
        errors={name: np.concatenate(values) for name, values in errors.items()},
        radii={name: np.concatenate(values) for name, values in radii.items()},
    )


def _row(room: str, case: Case, outcome: Outcome) -> str:
    cells = []
    for name in ("as given", "declared"):
        error, radius = outcome.errors[name], outcome.radii[name]
        cells.append(
            f"{100 * error.mean():.2f} | {np.mean(error <= radius):.3f} | "
            f"{100 * np.median(radius):.1f}"
        )
    # Paired per placement (the COUNT terminals of one trial share its draws).
    per_trial = {
        name: outcome.errors[name].reshape(-1, COUNT).mean(axis=1) for name in outcome.errors
    }
    difference = 100 * (per_trial["declared"] - per_trial["as given"])
    spread = difference.std(ddof=1) / math.sqrt(difference.size) if difference.size > 1 else 0.0
    return (
        f"| {room} | {case.name} | {cells[0]} | {cells[1]} | "
        f"{difference.mean():+.2f} +- {spread:.2f} |"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.tilt_spread``."""
    parser = argparse.ArgumentParser(prog="python -m bench.tilt_spread", description=__doc__)
    parser.add_argument("--trials", type=int, default=30, help="placements per case")
    parser.add_argument("--rooms", default="paper,hall", help="comma-separated rooms")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "docs")
    args = parser.parse_args(argv)
    rooms = [room.strip() for room in args.rooms.split(",") if room.strip()]
    started = time.perf_counter()
    lines = [
        "| room | case | as given: mean error (cm) | coverage | median radius (cm) "
        "| spread declared: mean error (cm) | coverage | median radius (cm) "
        "| paired difference (cm) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    with threadpool_limits(limits=1):
        for room in rooms:
            for case in CASES:
                lines.append(_row(room, case, run_case(room, case, args.trials)))
                print(lines[-1], file=sys.stderr, flush=True)
    elapsed = time.perf_counter() - started
    command = "python -m bench.tilt_spread " + " ".join(argv if argv is not None else sys.argv[1:])
    body = "\n".join(
        [
            "## A tilt spread declared in the layout, `terminals` form (`bench/tilt_spread.py`)",
            "",
            f"Command: `{command.strip()}` ({elapsed:.0f} s). K = {COUNT} terminals, "
            f"{SNR_DB:.0f} dB, {args.trials} placements per case; coverage: the fraction of "
            "terminals whose truth is inside `accuracy_m`.",
            "",
            "Machine:",
            "",
            machine_markdown(machine_record()),
            "",
            *lines,
        ]
    )
    path = args.out / "results" / "tilt-spread.md"
    replace_section(path, "tilt-spread", body, preamble="# Results: a tilt spread declared\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
