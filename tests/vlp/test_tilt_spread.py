"""``grid.receiver_tilt_sd``: the radii hold what tilts of the layout's spread move the
estimates by, checked against refits of the same measurement with one photodiode tilted."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.vlp.channel import los_gains
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import (
    Impairments,
    noise_std_for_snr,
    random_positions,
    simulate_terminals,
)
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver

TILT_SD_DEG = 4.0
STEP_RAD = 0.01  # a small tilt: the refits' response is linear in it
TRUTH = np.array([[1.3, 1.1], [2.9, 3.2], [0.9, 3.4]])


@pytest.fixture(scope="module")
def rooms() -> tuple[Layout, Fingerprint, Fingerprint]:
    level = paper_layout()
    tilted = dataclasses.replace(
        level, grid=dataclasses.replace(level.grid, receiver_tilt_sd=TILT_SD_DEG)
    )
    return level, build_fingerprint(level), build_fingerprint(tilted)


def _amplitudes(layout: Layout, normals: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(K, M) amplitudes of the receivers at TRUTH with these photodiode normals."""
    points = np.column_stack((TRUTH, np.full(len(TRUTH), layout.grid.receiver_height)))
    gains = los_gains(layout, points, normals)  # (M, K)
    return np.asarray((gains * layout.pilot_amplitudes[:, None]).T + noise)


def _tilted_normals(target: int, axis: int) -> np.ndarray:
    normals = np.tile([0.0, 0.0, 1.0], (len(TRUTH), 1))
    normals[target, axis] = STEP_RAD
    return np.asarray(normals / np.linalg.norm(normals, axis=1, keepdims=True))


@pytest.mark.parametrize("form", ["correlation", "terminals"])
def test_the_added_covariance_is_what_refits_of_tilted_photodiodes_move(
    rooms: tuple[Layout, Fingerprint, Fingerprint], form: str
) -> None:
    layout, level_fingerprint, tilted_fingerprint = rooms
    k, n_leds = len(TRUTH), layout.n_leds
    rng = np.random.default_rng(3)
    noise = noise_std_for_snr(level_fingerprint, 30.0) * rng.standard_normal((k, n_leds))
    level_normals = np.tile([0.0, 0.0, 1.0], (k, 1))

    # A terminal whose fit frees its tilt is not widened (with the spread declared it always
    # does, test below): the widening is that of terminals held level (tilt_sd None).
    options = GridlessOptions(tilt_sd=None) if form == "terminals" else GridlessOptions()

    def solve(fingerprint: Fingerprint, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        solver = GridlessSolver(fingerprint, "correlation", options)
        amplitudes = _amplitudes(layout, normals, noise)
        if form == "terminals":
            solution = solver.solve_terminals(amplitudes)
        else:
            measurement = measurement_from_amplitudes(amplitudes, "correlation", n_leds)
            solution = solver.solve(measurement, k)
        assert solution.covariances is not None
        order = np.argmin(
            np.linalg.norm(TRUTH[:, None, :] - solution.positions[None, :, :], axis=2), axis=1
        )
        assert len(set(order.tolist())) == k
        return solution.positions[order], solution.covariances[order]

    positions, without = solve(level_fingerprint, level_normals)
    assert np.linalg.norm(positions - TRUTH, axis=1).max() < 0.15
    same, with_spread = solve(tilted_fingerprint, level_normals)
    np.testing.assert_array_equal(same, positions)  # the spread changes radii, not positions
    added = with_spread - without
    # Independent: move each photodiode's normal a little, refit, and sum the squared moves.
    expected = np.zeros((k, 2, 2))
    for target in range(k):
        for axis in (0, 1):
            moved, _ = solve(level_fingerprint, _tilted_normals(target, axis))
            per_radian = (moved - positions) / STEP_RAD  # (K, 2)
            expected += np.einsum("ka,kb->kab", per_radian, per_radian)
    expected *= math.radians(TILT_SD_DEG) ** 2
    for got, want in zip(added, expected, strict=True):
        assert np.linalg.norm(got - want) <= 0.2 * np.linalg.norm(want)
    # Not a formality: the tilts' share is a real part of the radius.
    assert np.all(np.trace(added, axis1=1, axis2=2) > 0.2 * np.trace(without, axis1=1, axis2=2))


def test_terminals_whose_room_declares_a_tilt_spread_are_fitted_tilted_and_land_closer() -> None:
    # Hand-held photodiodes tilted 0-20 degrees: declared in the layout, each terminal's tilt
    # is fitted with that spread as its prior (a tilt is nearly a shift, so the significance
    # test alone kept most terminals level and moved them by the tilt instead).
    impairments = Impairments.tilts(20.0)
    level = paper_layout()
    declared = dataclasses.replace(
        level,
        grid=dataclasses.replace(level.grid, receiver_tilt_sd=impairments.tilt_component_sd_deg),
    )
    undeclared_solver = GridlessSolver(build_fingerprint(level), "correlation")
    declared_solver = GridlessSolver(build_fingerprint(declared), "correlation")
    errors: dict[str, list[float]] = {"undeclared": [], "declared": []}
    for seed in range(8):
        rng = np.random.default_rng(seed)
        truth = random_positions(level, 8, rng=rng)
        simulated = simulate_terminals(level, truth, impairments, snr_db=30.0, rng=rng)
        for name, solver in (("undeclared", undeclared_solver), ("declared", declared_solver)):
            found = solver.solve_terminals(simulated.amplitudes).positions
            errors[name] += np.linalg.norm(found - truth, axis=1).tolist()
    undeclared, fitted = np.mean(errors["undeclared"]), np.mean(errors["declared"])
    assert fitted < 0.9 * undeclared  # the same solver without the declaration: 1.0
    # Not a formality: the tilts really cost the undeclared fit (level terminals: ~2.5 cm).
    assert undeclared > 0.06
