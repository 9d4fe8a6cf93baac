"""How often the truth falls inside the answers' 95 % radius (``accuracy_m``).

The default solver reports, per estimate, the radius of the 95 % confidence circle of its
fit's covariance (noise and the model errors its residuals show, see
:mod:`app.vlp.uncertainty`). This counts, over fixed-seed placements (30 dB unless
``--snr``), the fraction of true positions inside that radius around their
(Hungarian-matched) estimate, with the median radius next to the median error (a radius
must not cover by being huge), for the aggregated correlation and the ``terminals`` form,
on the ideal model (as is, then with the layout saying the photodiodes are level,
``grid.receivers_level``) and under the realistic mix (reflectance in the layout; then also
with the mix's tilt spread in the layout, ``grid.receiver_tilt_sd``, and with its tilted
photodiodes wrongly declared level), in the paper room and the irregular room of
``bench/rooms.py``.

    python -m bench.coverage             # writes its section of docs/results/coverage.md
    python -m bench.coverage --trials 10 --out bench/out/quick
    python -m bench.coverage --snr 20 --rooms hall --out bench/out/hall20
    python -m bench.coverage --model power    # the aggregated power vector (CSM-VLP) instead
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from threadpoolctl import threadpool_limits

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Reflectance
from app.vlp.measurements import Model, measurement_from_amplitudes
from app.vlp.radii import confidence_radius
from app.vlp.simulation import Impairments
from app.vlp.solvers.gridless import GridlessSolver

from ._common import REPO_ROOT, machine_markdown, machine_record, replace_section
from ._real_rooms_extra import draw_terminals
from .real_rooms import MIX, _fingerprint, _generator, _layout

__all__ = ["Cell", "coverage", "main"]

KS = (1, 4, 8)
SNR_DB = 30.0
# The mix's tilts as the layout's spread (each tilt component's standard deviation).
MIX_TILT_SD_DEG = MIX.tilt_component_sd_deg
# What a layout may say about the photodiodes (``grid`` fields; none: the default).
TILT_SPREAD = (("receiver_tilt_sd", MIX_TILT_SD_DEG),)
LEVEL = (("receivers_level", True),)
# (mix, what the layout's grid says about the photodiodes) and the table's name for each
# condition.
CONDITIONS: tuple[tuple[bool, tuple[tuple[str, object], ...], str], ...] = (
    (False, (), "ideal"),
    (False, LEVEL, "ideal, photodiodes level in layout"),
    (True, (), "realistic mix, reflectance in layout"),
    (True, TILT_SPREAD, "realistic mix, reflectance and tilt spread in layout"),
    # What a wrong declaration costs: hand-held (tilted) terminals declared level.
    (True, LEVEL, "realistic mix, reflectance in layout, photodiodes wrongly declared level"),
)


@dataclass(frozen=True)
class Cell:
    """One cell of the table, per form: the fraction of truths inside the 95 % radius, the
    median radius and the median error (metres)."""

    inside: dict[str, float]
    radius: dict[str, float]
    error: dict[str, float]


def coverage(
    room: str,
    mix: bool,
    count: int,
    trials: int,
    snr_db: float = SNR_DB,
    model: Model = "correlation",
    photodiodes: tuple[tuple[str, object], ...] = (),
) -> Cell:
    """Coverage of the 95 % radius for the aggregated ``model`` (key ``"aggregated"``) and
    the terminals (key ``"terminals"``); ``photodiodes`` are the layout's ``grid`` fields
    about them (:data:`TILT_SPREAD`, :data:`LEVEL`; the same placements and draws as
    without)."""
    reflectance = MIX.reflectance if mix else None
    if photodiodes:
        fingerprint = _declared_fingerprint(room, reflectance, photodiodes)
        layout = fingerprint.layout
    else:
        layout = _layout(room, reflectance)
        fingerprint = _fingerprint(room, reflectance)
    solver = GridlessSolver(fingerprint, "correlation")
    aggregated = solver if model == "correlation" else GridlessSolver(fingerprint, model)
    impairments = MIX if mix else Impairments.ideal()
    inside: dict[str, list[bool]] = {"aggregated": [], "terminals": []}
    radii: dict[str, list[float]] = {"aggregated": [], "terminals": []}
    errors: dict[str, list[float]] = {"aggregated": [], "terminals": []}
    for trial in range(trials):
        truth, simulated = draw_terminals(
            layout,
            count,
            impairments,
            snr_db=snr_db,
            placement_rng=_generator("coverage", room, count, trial),
            noise_rng=_generator("coverage", room, mix, count, trial),
        )
        amplitudes = simulated.amplitudes
        measurement = measurement_from_amplitudes(amplitudes, model, layout.n_leds)
        for mode, solution in (
            ("aggregated", aggregated.solve(measurement, count)),
            ("terminals", solver.solve_terminals(amplitudes)),
        ):
            assert solution.covariances is not None
            distance = np.linalg.norm(truth[:, None, :] - solution.positions[None, :, :], axis=2)
            rows, cols = linear_sum_assignment(distance)
            for row, col in zip(rows, cols, strict=True):
                radius = confidence_radius(solution.covariances[col])
                inside[mode].append(bool(distance[row, col] <= radius))
                radii[mode].append(radius)
                errors[mode].append(float(distance[row, col]))
    return Cell(
        {mode: float(np.mean(values)) for mode, values in inside.items()},
        {mode: float(np.median(values)) for mode, values in radii.items()},
        {mode: float(np.median(values)) for mode, values in errors.items()},
    )


@cache
def _declared_fingerprint(
    room: str, reflectance: Reflectance | None, photodiodes: tuple[tuple[str, object], ...]
) -> Fingerprint:
    """The room's fingerprint with ``photodiodes`` in its layout's grid (built once)."""
    layout = _layout(room, reflectance)
    grid = dataclasses.replace(layout.grid, **dict(photodiodes))  # type: ignore[arg-type]
    return build_fingerprint(dataclasses.replace(layout, grid=grid))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m bench.coverage``."""
    parser = argparse.ArgumentParser(prog="python -m bench.coverage", description=__doc__)
    parser.add_argument("--trials", type=int, default=40, help="placements per cell")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "docs")
    parser.add_argument("--snr", type=float, default=SNR_DB, help="SNR in dB")
    parser.add_argument("--rooms", default="paper,hall", help="comma-separated rooms")
    parser.add_argument(
        "--model",
        choices=("correlation", "power"),
        default="correlation",
        help="the aggregated form (power: its own section, coverage-power)",
    )
    args = parser.parse_args(argv)
    rooms = [room.strip() for room in args.rooms.split(",") if room.strip()]
    started = time.perf_counter()
    lines = [
        f"| room | model | K | aggregated {args.model}: coverage | median radius / error (cm) "
        "| `terminals`: coverage | median radius / error (cm) |",
        "|---|---|---|---|---|---|---|",
    ]
    with threadpool_limits(limits=1):
        for room in rooms:
            for mix, photodiodes, name in CONDITIONS:
                for count in KS:
                    cell = coverage(
                        room, mix, count, args.trials, args.snr, args.model, photodiodes
                    )
                    parts = [
                        f"{cell.inside[mode]:.3f} | {100 * cell.radius[mode]:.1f} / "
                        f"{100 * cell.error[mode]:.1f}"
                        for mode in ("aggregated", "terminals")
                    ]
                    lines.append(f"| {room} | {name} | {count} | {parts[0]} | {parts[1]} |")
                    print(lines[-1], file=sys.stderr, flush=True)
    elapsed = time.perf_counter() - started
    command = "python -m bench.coverage " + " ".join(argv if argv is not None else sys.argv[1:])
    body = "\n".join(
        [
            "## Coverage of the 95 % radius (`bench/coverage.py`)"
            if args.model == "correlation"
            else f"## Coverage of the 95 % radius, {args.model} model (`bench/coverage.py`)",
            "",
            f"Command: `{command.strip()}` ({elapsed:.0f} s), {args.snr:g} dB, {args.trials} "
            "placements "
            "per cell: the fraction of true positions inside `accuracy_m` of their estimate "
            "(target 0.90-0.98 on the ideal model).",
            "",
            "Machine:",
            "",
            machine_markdown(machine_record()),
            "",
            *lines,
            "",
        ]
    )
    path = args.out / "results" / "coverage.md"
    tag = "coverage" if args.model == "correlation" else f"coverage-{args.model}"
    replace_section(path, tag, body, preamble="# Results: coverage of the 95 % radius\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
