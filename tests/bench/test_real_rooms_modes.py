"""Smoke tests of bench.real_rooms: its bound and calibration modes, solver options, rooms."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pytest

from app.vlp.crlb import aggregated_crlb
from app.vlp.fingerprints import build_fingerprint
from app.vlp.solvers.gridless import GridlessSolver
from bench import real_rooms
from bench._real_rooms_extra import BOUND_CASES, CALIBRATIONS, run_bounds, run_calibrated, tilt_sd
from bench.rooms import make_room
from tests.bench_rooms import SMALL_ROOM_SIDE_M

pytestmark = pytest.mark.slow


def test_bounds_mode_rows_and_the_ideal_case_is_the_aggregated_bound() -> None:
    rows = run_bounds(["paper"], 1, (4,), real_rooms._placements, real_rooms._noise_std)
    assert len(rows) == len(BOUND_CASES) * 2
    assert all(math.isfinite(r[5]) and r[5] > 0 for r in rows)
    ideal = next(r for r in rows if r[1] == BOUND_CASES[0].name and r[4] == "correlation")
    pts = real_rooms._placements("paper", 4, 0)
    layout = real_rooms._layout("paper", None)
    expected = aggregated_crlb(layout, pts, real_rooms._noise_std("paper")).mean
    assert ideal[5] == pytest.approx(expected, rel=1e-9)
    # Every case with nuisances costs at least what the known model does (same placement).
    known = {r[4]: r[5] for r in rows if r[1] == BOUND_CASES[0].name}
    for case in BOUND_CASES[2:4]:
        for mode in ("correlation", "terminals"):
            value = next(r[5] for r in rows if r[1] == case.name and r[4] == mode)
            assert value >= known[mode]


def test_tilt_sd_of_a_uniform_polar_angle() -> None:
    # Small angles: tan(theta) ~ theta, E[theta^2] = max^2 / 3, half of it on each axis.
    assert tilt_sd(1.0) == pytest.approx(math.radians(1.0) / math.sqrt(6), rel=1e-3)


def test_calibrated_mode_runs_every_calibration(small_room: str) -> None:
    rows = run_calibrated(
        [small_room],
        1,
        real_rooms.MIX,
        "realistic mix, reflectance in layout",
        real_rooms._generator,
        count=2,
    )
    assert [r[1] for r in rows[::2]] == [c.name for c in CALIBRATIONS]
    # Every calibration's answers are near the truth (they are 4-16 cm off; a guess
    # anywhere in the room would be a metre off on average).
    assert all(math.isfinite(r[5]) and 0 <= r[5] < 0.2 * SMALL_ROOM_SIDE_M for r in rows)


def test_an_option_builds_the_default_solver_with_it(tmp_path: Path) -> None:
    assert real_rooms._parse_option("tolerance_jumps=False") == ("tolerance_jumps", False)
    with pytest.raises(argparse.ArgumentTypeError, match="not a GridlessOptions field"):
        real_rooms._parse_option("jumps=False")
    with pytest.raises(argparse.ArgumentTypeError, match="not a Python literal"):
        real_rooms._parse_option("tolerance_jumps=maybe")
    try:
        real_rooms.main(
            [
                "--rooms",
                "office",
                "--conditions",
                "ideal",
                "--trials",
                "1",
                "--option",
                "tolerance_jumps=False",
                "--snr",
                "40",
                "--out",
                str(tmp_path),
            ]
        )
        built = [s for s in real_rooms._SOLVERS.values() if isinstance(s, GridlessSolver)]
        assert built and all(not s.options.tolerance_jumps for s in built)
        assert "40 dB" in (tmp_path / "results" / "real-rooms.md").read_text()
    finally:
        real_rooms._OPTIONS.clear()
        real_rooms._SOLVERS.clear()


@pytest.mark.parametrize(
    ("name", "n_leds", "n_cells"), [("office", 12, 630), ("corridor", 16, 480)]
)
def test_the_check_rooms_are_the_ones_their_docstrings_describe(
    name: str, n_leds: int, n_cells: int
) -> None:
    layout = make_room(name)
    assert (layout.n_leds, layout.n_cells) == (n_leds, n_cells)
    # Small rooms: the solver's dense path, where the joint fit and its moves run.
    assert build_fingerprint(layout).is_dense
