"""Each stage of the default solver on and off, on the measured survey and on the simulator.

Run from the repository root on a fetched copy of the Massey University survey (see
:mod:`bench.measured`)::

    python -m bench.ablation DATA                      # writes docs/results/ablation.md
    python -m bench.ablation DATA --max-test 100 --trials 2 --out bench/out/quick

A stage is switched off through its :class:`GridlessOptions` field (:data:`VARIANTS`); every
other setting stays the default. Measured: the protocol of :mod:`bench.measured` (nominal
layout, a survey of about one point per square metre, calibration through the API), the rooms
made and calibrated once, then for each variant a fresh service process on the same data
answers the same test points through ``POST .../localize/batch``: K = 1 as `terminals` on the
calibrated and on the nominal layout, K = 2 as aggregated correlation on the calibrated one;
"5 LEDs" is the same protocol with five of the eleven luminaires (a room with few LEDs per
terminal, where nuisances are the least determined). Simulated: :mod:`bench.real_rooms`'s paper
room, ideal and realistic mix, K = 1, 4, 8 aggregated and K = 8 `terminals`, the same seeded
placements for every variant. Cells are mean errors in cm (median for the measured K = 1).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import Model
from app.vlp.solvers import base as solver_registry
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver

from . import real_rooms
from ._common import REPO_ROOT, machine_markdown, machine_record, write_csv
from ._massey import (
    FIVE_LEDS,
    MIN_DETECTED,
    MasseySurvey,
    estimate_receiver_height,
    facility_split,
    load_survey,
    shown_command,
)
from .measured import (
    HEIGHT_CANDIDATES_M,
    Row,
    _service,
    calibrate,
    create_room,
    layout_body,
    nominal_scale,
    service_rows,
)

__all__ = ["VARIANTS", "Variant", "main"]


@dataclass(frozen=True)
class Variant:
    """One line of the table: a stage and the options that switch it off."""

    name: str
    options: dict[str, object] = field(default_factory=dict)


VARIANTS: tuple[Variant, ...] = (
    Variant("default"),
    Variant("no per-target gains (nor common scale)", {"log_gain_sd": None}),
    Variant("no common scale", {"log_scale_sd": None}),
    Variant("no terminal tilt fit", {"tilt_sd": None}),
    Variant("no LED-error weights (terminals)", {"terminal_led_weights": False}),
    Variant("no weighted-pass starts (terminals)", {"weighted_pass_starts": False}),
    Variant("no room tolerances", {"led_log_amplitude_sd": None}),
    Variant("no tilts after tolerances", {"tolerance_tilt_sd": 0.0}),
    Variant("no far places", {"relocate_ambiguous": False}),
    Variant("no far relocation", {"relocate_far": False}),
    Variant("no relocation", {"relocate_passes": 0}),
    Variant("no rescaled search", {"rescale_search": None}),
    Variant("no restarts", {"restarts": 0}),
    Variant("no whitening", {"whiten": False}),
)

MEASURED_COLUMNS = (
    "K=1 cal median",
    "K=1 cal mean",
    "K=1 cal coverage",
    "K=1 nominal median",
    "K=2 cal mean",
    "5 LEDs, K=1 cal median",
    "5 LEDs, K=1 nominal median",
)
_PROTOCOL = """Measured (Massey lobby, 11 luminaires; see [measured](measured.md)): the
nominal layout and a survey of about one point per square metre calibrated through the API
once; then, for each variant, a fresh service on the same rooms answers the same test points:
K = 1 `terminals` on the calibrated (`cal`) and the nominal layout, K = 2 aggregated
correlation on the calibrated one; "5 LEDs" is the same protocol with luminaires 4, 5, 7, 10
and 11 only, on the test points that detect at least three of them. Simulated ([realistic
rooms](real-rooms.md)): the paper room, ideal, realistic mix and tilted photodiodes, 30 dB,
the same seeded placements for every variant. Cells are errors in cm: the median where the
column says so, else the mean; coverage is the share of truths inside the 95 % radius."""
SIMULATED_CONDITIONS = ("ideal", "realistic mix", "tilt 0-20 deg")
SIMULATED_CELLS = (("correlation", 1), ("correlation", 4), ("correlation", 8), ("terminals", 8))


@contextmanager
def default_options(options: dict[str, object]) -> Iterator[None]:
    """The service's ``gridless`` solver built with ``options`` (the rest defaults) while
    inside: the registry entry the service's ``make_solver`` reads is swapped, in this process
    only."""
    original = solver_registry.SOLVERS["gridless"]

    def build(fingerprint: Fingerprint, model: Model) -> GridlessSolver:
        return GridlessSolver(fingerprint, model, GridlessOptions(**options))  # type: ignore[arg-type]

    solver_registry.SOLVERS["gridless"] = cast("Any", build)
    try:
        yield
    finally:
        solver_registry.SOLVERS["gridless"] = original


@dataclass(frozen=True)
class _Rooms:
    """A survey's nominal and calibrated rooms in one data folder, and its test points."""

    survey: MasseySurvey
    test: np.ndarray
    nominal_id: str
    calibrated_id: str


def prepare_rooms(
    survey: MasseySurvey, max_test: int | None, seed: int, data_dir: Path, min_detected: int = 0
) -> _Rooms:
    """Create and calibrate once (the default service): every variant reuses the rooms."""
    split = facility_split(survey.points, seed=seed, max_test=max_test)
    receiver_z, _ = estimate_receiver_height(survey, split.survey, HEIGHT_CANDIDATES_M)
    scale = nominal_scale(survey, split.survey, receiver_z)
    body = layout_body(survey, receiver_z, scale, level=False)
    with _service(data_dir) as client:
        nominal_id = create_room(client, body)
        calibrated_id = create_room(client, body)
        calibrate(client, calibrated_id, survey, split.survey, "null")
    seen = np.isfinite(survey.readings[split.test]).sum(axis=1)
    return _Rooms(survey, split.test[seen >= min_detected], nominal_id, calibrated_id)


def _pick(rows: Sequence[Row], k: int) -> Row:
    return next(row for row in rows if row.k == k)


def measured_cells(
    rooms: _Rooms, few: _Rooms, data_dir: Path, few_dir: Path, seed: int
) -> list[float]:
    """The measured columns (:data:`MEASURED_COLUMNS`) under the options in force."""
    with _service(data_dir) as client:
        calibrated = service_rows(
            client, rooms.calibrated_id, rooms.survey, rooms.test, "calibrated", "null", seed
        )
        nominal = service_rows(
            client, rooms.nominal_id, rooms.survey, rooms.test, "nominal", "null", seed
        )
    with _service(few_dir) as client:
        few_calibrated = service_rows(
            client, few.calibrated_id, few.survey, few.test, "calibrated", "null", seed
        )
        few_nominal = service_rows(
            client, few.nominal_id, few.survey, few.test, "nominal", "null", seed
        )
    one = _pick(calibrated, 1)
    return [
        float(np.median(one.errors_cm)),
        float(np.mean(one.errors_cm)),
        float(np.mean(one.errors_cm <= one.radii_cm)),
        float(np.median(_pick(nominal, 1).errors_cm)),
        float(np.mean(_pick(calibrated, 2).errors_cm)),
        float(np.median(_pick(few_calibrated, 1).errors_cm)),
        float(np.median(_pick(few_nominal, 1).errors_cm)),
    ]


def simulated_cells(options: dict[str, object], trials: int) -> list[float]:
    """Mean errors (cm) per (condition, form, K) of :data:`SIMULATED_CELLS`."""
    conditions = [c for c in real_rooms.CONDITIONS if c.name in SIMULATED_CONDITIONS]
    real_rooms.set_options(options)
    try:
        rows = real_rooms.run(["paper"], conditions, trials, progress=False)
    finally:
        real_rooms.set_options({})
    cells = []
    for condition in SIMULATED_CONDITIONS:
        for mode, k in SIMULATED_CELLS:
            errors = [r[5] for r in rows if r[1] == condition and r[2] == k and r[4] == mode]
            cells.append(100 * float(np.nanmean(errors)))
    return cells


def simulated_columns() -> list[str]:
    """Headers of :func:`simulated_cells`, in its order."""
    return [f"{c}, {m} K={k}" for c in SIMULATED_CONDITIONS for m, k in SIMULATED_CELLS]


def run(
    survey: MasseySurvey,
    variants: Sequence[Variant],
    *,
    max_test: int | None,
    trials: int,
    seed: int,
    tmp: Path,
    progress: Callable[[str], None] = print,
) -> list[list[object]]:
    """One row per variant: its name, then the measured and simulated columns."""
    few_survey = survey.with_leds([name - 1 for name in FIVE_LEDS])
    data_dir, few_dir = tmp / "all", tmp / "five"
    rooms = prepare_rooms(survey, max_test, seed, data_dir)
    few = prepare_rooms(few_survey, max_test, seed, few_dir, MIN_DETECTED)
    table: list[list[object]] = []
    for variant in variants:
        with default_options(variant.options):
            measured = measured_cells(rooms, few, data_dir, few_dir, seed)
        simulated = simulated_cells(variant.options, trials)
        table.append([variant.name, *(round(v, 2) for v in measured + simulated)])
        progress(f"{variant.name}: {table[-1][1:]}")
    return table


def _markdown(header: Sequence[str], table: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for row in table:
        cells = [str(row[0])] + [
            "-" if isinstance(v, float) and math.isnan(v) else f"{v}" for v in row[1:]
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_page(
    variants: Sequence[Variant],
    header: Sequence[str],
    table: Sequence[Sequence[object]],
    command: str,
    out: Path,
    csv: Path,
) -> None:
    """The results page and its CSV."""
    write_csv(csv, header, table)
    cut = 1 + len(MEASURED_COLUMNS)  # the name, then the measured columns
    shown = csv.relative_to(REPO_ROOT) if csv.is_relative_to(REPO_ROOT) else csv
    options = "\n".join(
        f"- {v.name}: `{', '.join(f'{k}={val!r}' for k, val in v.options.items()) or 'defaults'}`"
        for v in variants
    )
    text = f"""# Ablation: each stage of the default solver on and off

Generated by `{command}` (CSV: `{shown}`).

{_PROTOCOL}

A stage is switched off with these options (`GridlessOptions`), every other setting default:

{options}

Measured (errors in cm):

{_markdown(header[:cut], [row[:cut] for row in table])}

Simulated (mean errors in cm; "tilt 0-20 deg": photodiodes tilted, the layout silent about it):

{_markdown([header[0], *header[cut:]], [[row[0], *row[cut:]] for row in table])}

The far relocation acts on the power model and the rescaled search where K is counted from the
correlation matrix's rank: neither is in these cells, where switching them off changes nothing.

Machine:

{machine_markdown(machine_record())}
"""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(prog="python -m bench.ablation", description=__doc__)
    parser.add_argument("data", type=Path, help="fetched copy (directory or bare git dir)")
    parser.add_argument("--commit", default=None, help="commit to read from a git directory")
    parser.add_argument("--max-test", type=int, default=300, help="measured test points")
    parser.add_argument("--trials", type=int, default=10, help="simulated trials per cell")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", default=None, help="comma-separated variant numbers (0 first)")
    parser.add_argument("--out", type=Path, default=None, help="default: docs/ (full run)")
    args = parser.parse_args(argv)
    survey = load_survey(args.data, args.commit)
    variants = [VARIANTS[int(i)] for i in args.only.split(",")] if args.only else list(VARIANTS)
    with tempfile.TemporaryDirectory(prefix="vlp-ablation-") as tmp:
        table = run(
            survey,
            variants,
            max_test=args.max_test or None,
            trials=args.trials,
            seed=args.seed,
            tmp=Path(tmp),
            progress=lambda text: print(text, file=sys.stderr, flush=True),
        )
    header = ["variant", *MEASURED_COLUMNS, *simulated_columns()]
    given = sys.argv[1:] if argv is None else argv
    command = shown_command("python -m bench.ablation", given, args.data)
    out = args.out or REPO_ROOT / "docs" / "results"
    csv_path = (args.out or REPO_ROOT / "docs" / "data") / "ablation.csv"
    write_page(variants, header, table, command, out / "ablation.md", csv_path)
    print(_markdown(header, table))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
