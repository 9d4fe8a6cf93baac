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
from app.vlp.simulation import noise_std_for_snr
from app.vlp.solvers.gridless import GridlessSolver

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

    def solve(fingerprint: Fingerprint, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        solver = GridlessSolver(fingerprint, "correlation")
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
