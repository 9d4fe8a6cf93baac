"""Accuracy in rooms that are not the paper's model: reflections, gains, heights, tilts, LEDs.

Run from the repository root::

    python -m bench.real_rooms                 # 30 trials per cell, writes under docs/
    python -m bench.real_rooms --quick         # 3 trials, paper room, under bench/out/quick/
    python -m bench.real_rooms --bounds        # Cramer-Rao bounds with nuisances, same placements
    python -m bench.real_rooms --calibrated    # realistic mix, K = 8, before / after a survey
    python -m bench.real_rooms --rooms office,corridor --option tolerance_jumps=False --snr 40
                                               # other rooms, a solver option, another SNR

For each room (the paper's and the irregular ``hall`` of :mod:`bench.rooms`), condition
(:data:`CONDITIONS`), K in {1, 4, 8} and trial, K terminals are placed uniformly in the room
(no two in one grid cell) and :func:`app.vlp.simulation.simulate_terminals` draws the
condition's impairments and the noisy amplitudes at 30 dB. The placements depend only on
(room, K, trial), so every condition sees the same terminals. Two ways to locate them:

- ``correlation``: the K terminals' amplitudes aggregated into ``R = sum_k a_k a_k^T`` and one
  K-target solve;
- ``terminals``: each terminal's own amplitudes, fitted terminal by terminal (the service's
  ``terminals`` form with the default solver).

The error of a trial is the mean distance between estimates and truth after optimal
(Hungarian) matching; the table shows the mean over trials, in centimetres. Conditions
marked "in layout" give the service a layout whose ``room.reflectance`` matches the truth,
so its fingerprint includes the reflections; the others give it the line-of-sight layout.
"""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import math
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.measurements import Measurement, Model, measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.simulation import (
    Impairments,
    noise_std_for_snr,
    random_positions,
)
from app.vlp.solvers import Solver, make_solver
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from app.vlp.typing import FloatArray

from ._common import (
    REPO_ROOT,
    load_solvers,
    machine_markdown,
    machine_record,
    replace_section,
    write_csv,
)
from ._real_rooms_extra import (
    BOUND_CASES,
    CALIBRATIONS,
    draw_terminals,
    run_bounds,
    run_calibrated,
)
from .rooms import make_room

__all__ = [
    "CONDITIONS",
    "Condition",
    "Localizer",
    "gridless_localizer",
    "main",
    "run",
    "set_options",
]

SEED = 20261123
SNR_DB = 30.0
# A results page written where none exists yet (the generated sections are appended to it).
PREAMBLE = "# Results: realistic rooms\n"
KS = (1, 4, 8)
MODES = ("correlation", "terminals")

Localizer = Callable[[Fingerprint, Measurement, int], FloatArray]


@dataclass(frozen=True)
class Condition:
    """One row of the table: what the room really does, and what the layout tells."""

    name: str
    impairments: Impairments
    reflectance_in_layout: Reflectance | None = None
    height_sd_in_layout: float = 0.0
    # grid.receiver_tilt_sd, degrees (the condition's own tilt spread, as an admin who knows
    # how the phones are held would set it).
    tilt_sd_in_layout: float = 0.0


WALLS = Reflectance(walls=0.7, floor=0.0, ceiling=0.0)
MIX = Impairments.realistic_mix()

CONDITIONS: tuple[Condition, ...] = (
    Condition("ideal", Impairments.ideal()),
    Condition("reflections 0.7", Impairments.reflections(0.7)),
    Condition("reflections 0.7, in layout", Impairments.reflections(0.7), WALLS),
    Condition("gain sd 10 %", Impairments.gain_spread(0.10)),
    Condition("heights sd 15 cm", Impairments.heights(0.15)),
    Condition("heights sd 15 cm, sd in layout", Impairments.heights(0.15), None, 0.15),
    Condition("tilt 0-20 deg", Impairments.tilts(20.0)),
    Condition(
        "tilt 0-20 deg, spread in layout",
        Impairments.tilts(20.0),
        tilt_sd_in_layout=Impairments.tilts(20.0).tilt_component_sd_deg,
    ),
    Condition("LED 5 % / 3 deg", Impairments.led_tolerances(0.05, 3.0)),
    Condition("realistic mix", MIX),
    Condition("realistic mix, reflectance in layout", MIX, MIX.reflectance),
    Condition(
        "realistic mix, reflectance and height sd in layout",
        MIX,
        MIX.reflectance,
        MIX.height_sd_m,
    ),
    Condition(
        "realistic mix, reflectance, height and tilt sd in layout",
        MIX,
        MIX.reflectance,
        MIX.height_sd_m,
        MIX.tilt_component_sd_deg,
    ),
)


def gridless_localizer(
    fingerprint: Fingerprint, measurement: Measurement, count: int
) -> FloatArray:
    """Today's default: the ``gridless`` solver, one per (fingerprint, model), reused."""
    return _solver(fingerprint, measurement.model).solve(measurement, count).positions


_SOLVERS: dict[tuple[int, Model, tuple[tuple[str, object], ...]], Solver] = {}
# GridlessOptions fields the default solver is built with (``--option``; empty: defaults).
_OPTIONS: dict[str, object] = {}


def set_options(options: dict[str, object]) -> None:
    """Build the default solver with these GridlessOptions fields from now on (empty: the
    defaults); solvers already built with other options are kept under their own key."""
    _OPTIONS.clear()
    _OPTIONS.update(options)


def _solver(fingerprint: Fingerprint, model: Model) -> Solver:
    # The options are part of the key: a run that changes them gets new solvers.
    key = (id(fingerprint), model, tuple(sorted(_OPTIONS.items())))
    if key not in _SOLVERS:
        _SOLVERS[key] = (
            GridlessSolver(fingerprint, model, GridlessOptions(**_OPTIONS))  # type: ignore[arg-type]
            if _OPTIONS
            else make_solver("gridless", fingerprint, model)
        )
    return _SOLVERS[key]


def _parse_option(text: str) -> tuple[str, object]:
    """``NAME=VALUE`` of ``--option``: a GridlessOptions field and a Python literal."""
    name, _, value = text.partition("=")
    fields = {field.name for field in dataclasses.fields(GridlessOptions)}
    if name not in fields:
        raise argparse.ArgumentTypeError(f"{name!r} is not a GridlessOptions field")
    try:
        return name, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(f"{value!r} is not a Python literal") from None


@cache
def _layout(
    room: str, reflectance: Reflectance | None, height_sd: float = 0.0, tilt_sd: float = 0.0
) -> Layout:
    layout = make_room(room)
    return dataclasses.replace(
        layout,
        room=dataclasses.replace(layout.room, reflectance=reflectance),
        grid=dataclasses.replace(
            layout.grid, receiver_height_sd=height_sd, receiver_tilt_sd=tilt_sd
        ),
    )


@cache
def _fingerprint(
    room: str, reflectance: Reflectance | None, height_sd: float = 0.0, tilt_sd: float = 0.0
) -> Fingerprint:
    return build_fingerprint(_layout(room, reflectance, height_sd, tilt_sd))


def _generator(*key: object) -> np.random.Generator:
    words = tuple(zlib.crc32(str(part).encode()) for part in key)
    return np.random.default_rng(np.random.SeedSequence(SEED, spawn_key=words))


def run_trial(
    room: str,
    condition: Condition,
    count: int,
    trial: int,
    localize: Localizer,
    snr_db: float = SNR_DB,
) -> dict[str, float]:
    """Mean matched error (metres) of each mode in one trial; NaN where the solve failed."""
    told = (
        condition.reflectance_in_layout,
        condition.height_sd_in_layout,
        condition.tilt_sd_in_layout,
    )
    layout = _layout(room, *told)
    positions, simulated = draw_terminals(
        layout,
        count,
        condition.impairments,
        snr_db=snr_db,
        placement_rng=_generator(room, count, trial),
        noise_rng=_generator(room, condition.name, count, trial),
    )
    fingerprint = _fingerprint(room, *told)
    amplitudes = simulated.amplitudes
    errors: dict[str, float] = {}
    try:
        together = measurement_from_amplitudes(amplitudes, "correlation", layout.n_leds)
        errors["correlation"] = mean_position_error(
            localize(fingerprint, together, count), positions
        )
    except Exception:  # a failing solve is counted, not fatal
        errors["correlation"] = float("nan")
    try:
        # The service's `terminals` form: each terminal fitted from its own amplitudes.
        solver = _solver(fingerprint, "correlation")
        assert isinstance(solver, GridlessSolver)
        errors["terminals"] = mean_position_error(
            solver.solve_terminals(amplitudes).positions, positions
        )
    except Exception:
        errors["terminals"] = float("nan")
    return errors


def run(
    rooms: Sequence[str],
    conditions: Sequence[Condition],
    trials: int,
    localize: Localizer = gridless_localizer,
    *,
    progress: bool = True,
    snr_db: float = SNR_DB,
) -> list[tuple[str, str, int, int, str, float]]:
    """Every (room, condition, K, trial, mode) error in metres."""
    rows: list[tuple[str, str, int, int, str, float]] = []
    started = time.perf_counter()
    cells = [(r, c, k) for r in rooms for c in conditions for k in KS]
    for done, (room, condition, count) in enumerate(cells, start=1):
        for trial in range(trials):
            errors = run_trial(room, condition, count, trial, localize, snr_db)
            rows += [(room, condition.name, count, trial, m, errors[m]) for m in MODES]
        if progress:
            elapsed = time.perf_counter() - started
            print(f"  {done}/{len(cells)} cells, {elapsed:.0f} s", file=sys.stderr, flush=True)
    return rows


def summary_table(
    rows: Sequence[tuple[str, str, int, int, str, float]], room: str, trials: int
) -> str:
    """Markdown table of the mean error (cm) per condition x (K, mode) for one room."""
    header = "| condition | " + " | ".join(f"K = {k}" for k in KS) + " | terminals, K = 8 |"
    lines = [header, "|---" * (len(KS) + 2) + "|"]
    names = list(dict.fromkeys(r[1] for r in rows if r[0] == room))
    for name in names:
        cells = []
        for count, mode in [(k, "correlation") for k in KS] + [(8, "terminals")]:
            values = [r[5] for r in rows if r[:3] == (room, name, count) and r[4] == mode]
            failed = sum(np.isnan(values))
            text = f"{100 * np.nanmean(values):.1f}" if len(values) > failed else "-"
            cells.append(text + (f" ({failed} failed)" if failed else ""))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + f"\n\n({trials} trials per cell, mean matched error in cm.)"


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m bench.real_rooms",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quick", action="store_true", help="3 trials, paper room only")
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (default 30)")
    parser.add_argument("--rooms", default=None, help="comma-separated subset of paper,hall")
    parser.add_argument("--out", type=Path, default=None, help="output folder")
    parser.add_argument(
        "--conditions",
        default=None,
        help="main table: a subset of the conditions, names separated by ';'",
    )
    parser.add_argument(
        "--achieved",
        type=Path,
        default=None,
        help="--bounds: the main table's CSV to compare with (default docs/data/real_rooms.csv)",
    )
    parser.add_argument(
        "--option",
        type=_parse_option,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="main table: build the default solver with this GridlessOptions field (repeatable)",
    )
    parser.add_argument(
        "--snr", type=float, default=SNR_DB, help=f"main table: SNR in dB (default {SNR_DB:g})"
    )
    parser.add_argument(
        "--first-trial",
        type=int,
        default=0,
        help="--calibrated: start at this trial (to split a run between processes)",
    )
    parser.add_argument(
        "--bounds",
        action="store_true",
        help="instead: the Cramer-Rao bounds with nuisances at the same placements",
    )
    parser.add_argument(
        "--calibrated",
        action="store_true",
        help="instead: the realistic mix at K = 8, uncalibrated vs after a survey calibration",
    )
    return parser.parse_args(argv)


def _noise_std(room: str) -> float:
    return noise_std_for_snr(_fingerprint(room, None), SNR_DB)


def _placements(room: str, count: int, trial: int) -> FloatArray:
    return random_positions(_layout(room, None), count, rng=_generator(room, count, trial))


Rows = Sequence[tuple[str, str, int, int, str, float]]


def _mean_cells(rows: Rows, room: str, name: str, count: int, mode: str) -> float:
    values = [r[5] for r in rows if r[:3] == (room, name, count) and r[4] == mode]
    return float(100 * np.nanmean(values)) if values else float("nan")


def bounds_table(
    rows: Sequence[tuple[str, str, int, int, str, float]],
    achieved: Sequence[tuple[str, str, int, int, str, float]],
    room: str,
    trials: int,
) -> str:
    """Markdown: bound (cm) per case x (K, mode), with the achieved K = 8 mean beside it."""
    lines = [
        "| case | K = 1 | K = 4 | K = 8 | terminals, K = 8 | achieved K = 8 (terminals) |",
        "|---|---|---|---|---|---|",
    ]
    for case in BOUND_CASES:
        cells = [f"{_mean_cells(rows, room, case.name, k, 'correlation'):.1f}" for k in KS]
        cells.append(f"{_mean_cells(rows, room, case.name, 8, 'terminals'):.1f}")
        done = _mean_cells(achieved, room, case.achieved, 8, "correlation")
        alone = _mean_cells(achieved, room, case.achieved, 8, "terminals")
        cells.append("-" if math.isnan(done) else f"{done:.1f} ({alone:.1f})")
        lines.append(f"| {case.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + (
        f"\n\n(bound: RMS position error sqrt(var_x + var_y) averaged over the targets, mean "
        f"over {trials} placements, cm; for Gaussian errors the mean error is 0.89x the RMS. "
        "Achieved: mean matched error of the main table's row, same placements.)"
    )


def _read_rows(path: Path) -> list[tuple[str, str, int, int, str, float]]:
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as handle:
        records = list(csv.reader(handle))[1:]
    return [
        (room, condition, int(k), int(trial), mode, float(error))
        for room, condition, k, trial, mode, error in records
    ]


def _section(
    out: Path, tag: str, title: str, command: str, elapsed: float, text: list[str]
) -> Path:
    body = [f"## {title}", "", f"Command: `{command.strip()}` ({elapsed:.0f} s).", ""]
    body += ["Machine:", "", machine_markdown(machine_record()), "", *text]
    path = out / "results" / "real-rooms.md"
    replace_section(path, tag, "\n".join(body), preamble=PREAMBLE)
    return path


def _main_bounds(args: argparse.Namespace, rooms: list[str], trials: int, command: str) -> int:
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    started = time.perf_counter()
    with threadpool_limits(limits=1):
        rows = run_bounds(rooms, trials, KS, _placements, _noise_std)
    elapsed = time.perf_counter() - started
    write_csv(
        out / "data" / "real_rooms_bounds.csv",
        ("room", "case", "k", "trial", "mode", "bound_m"),
        rows,
    )
    achieved = _read_rows(args.achieved or REPO_ROOT / "docs" / "data" / "real_rooms.csv")
    text = []
    for room in rooms:
        text += [f"### Room `{room}`", "", bounds_table(rows, achieved, room, trials), ""]
    path = _section(
        out,
        "real-rooms-bounds",
        "Bounds with nuisances (`bench/real_rooms.py --bounds`)",
        command,
        elapsed,
        text,
    )
    print(f"{len(rows)} rows, {elapsed:.0f} s; wrote {path}")
    return 0


def _main_calibrated(args: argparse.Namespace, rooms: list[str], trials: int, command: str) -> int:
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    started = time.perf_counter()
    name = "realistic mix, reflectance in layout"
    with threadpool_limits(limits=1):
        rows = run_calibrated(rooms, trials, MIX, name, _generator, first_trial=args.first_trial)
    elapsed = time.perf_counter() - started
    write_csv(
        out / "data" / "real_rooms_calibrated.csv",
        ("room", "calibration", "k", "trial", "mode", "error_m"),
        rows,
    )
    text = []
    for room in rooms:
        text += [
            f"### Room `{room}`",
            "",
            "| model used by the service | aggregated correlation, K = 8 | terminals, K = 8 |",
            "|---|---|---|",
        ]
        for calibration in CALIBRATIONS:
            cells = [
                f"{_mean_cells(rows, room, calibration.name, 8, mode):.1f}"
                for mode in ("correlation", "terminals")
            ]
            text.append(f"| {calibration.name} | " + " | ".join(cells) + " |")
        text += ["", f"({trials} trials, mean matched error in cm.)", ""]
    path = _section(
        out,
        "real-rooms-calibrated",
        "Realistic mix, uncalibrated vs survey calibration (`bench/real_rooms.py --calibrated`)",
        command,
        elapsed,
        text,
    )
    print(f"{len(rows)} rows, {elapsed:.0f} s; wrote {path}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; write ``data/real_rooms.csv`` and the measured section of
    ``results/real-rooms.md`` (between its ``real-rooms-bench`` markers) into ``--out``."""
    args = _parse_args(argv)
    load_solvers()
    trials = args.trials or (3 if args.quick else 30)
    rooms = (
        args.rooms.split(",") if args.rooms else (["paper"] if args.quick else ["paper", "hall"])
    )
    command = "python -m bench.real_rooms " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.bounds:
        return _main_bounds(args, rooms, trials, command)
    if args.calibrated:
        return _main_calibrated(args, rooms, trials, command)
    out = args.out or (REPO_ROOT / ("bench/out/quick" if args.quick else "docs"))
    started = time.perf_counter()
    conditions = CONDITIONS
    if args.conditions:
        wanted = args.conditions.split(";")
        conditions = tuple(c for c in CONDITIONS if c.name in wanted)
        if len(conditions) != len(wanted):
            raise SystemExit(f"unknown condition in {wanted}")
    set_options(dict(args.option))
    with threadpool_limits(limits=1):
        rows = run(rooms, conditions, trials, snr_db=args.snr)
    elapsed = time.perf_counter() - started
    write_csv(
        out / "data" / "real_rooms.csv",
        ("room", "condition", "k", "trial", "mode", "error_m"),
        rows,
    )
    body = [
        "## Measured (`bench/real_rooms.py`)",
        "",
        f"Command: `{command.strip()}` ({elapsed:.0f} s). Default solver (`gridless`), "
        f"{args.snr:g} dB, columns K = 1 / 4 / 8 aggregated correlation, then each of the "
        "K = 8 terminals sent as `terminals` (each fitted from its own amplitudes).",
        "",
        "Machine:",
        "",
        machine_markdown(machine_record()),
        "",
    ]
    for room in rooms:
        body += [f"### Room `{room}`", "", summary_table(rows, room, trials), ""]
    path = out / "results" / "real-rooms.md"
    replace_section(path, "real-rooms-bench", "\n".join(body), preamble=PREAMBLE)
    print(f"{len(rows)} rows, {elapsed:.0f} s; wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
