"""A layout whose photodiodes are level (``grid.receivers_level``): the radii allow no tilt.

Without it the answers' radii allow for photodiode tilts the residuals may hide (hand-held
phones): in a room exactly as modelled the model-error fit then puts a variance on tilts from
the noise in about half of the answers, and as a tilt is nearly a shift of the position those
radii are several times the errors (docs/decisions/receivers-level.md).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.radii import confidence_radii
from app.vlp.simulation import noise_std_for_snr, random_positions, true_amplitudes
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from app.vlp.typing import FloatArray


@pytest.fixture(scope="module")
def level_fingerprint(paper_room: Layout) -> Fingerprint:
    grid = dataclasses.replace(paper_room.grid, receivers_level=True)
    return build_fingerprint(dataclasses.replace(paper_room, grid=grid))


def _draws(
    paper_room: Layout, sigma: float, count: int, n: int, seed: int
) -> list[tuple[FloatArray, FloatArray]]:
    """``n`` placements of ``count`` level terminals and their noisy amplitudes."""
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(n):
        truth = random_positions(paper_room, count, rng=rng)
        noise = sigma * rng.standard_normal((count, paper_room.n_leds))
        draws.append((truth, true_amplitudes(paper_room, truth) + noise))
    return draws


def test_terminals_of_a_level_room_get_radii_at_their_level(
    paper_room: Layout, paper_fingerprint: Fingerprint, level_fingerprint: Fingerprint
) -> None:
    """Eight level terminals, 30 dB, 25 placements: each terminal's radius (estimate k is
    terminal k) in the layout that says so covers its truth about 95 % of the time, at 2.1x
    (a round Gaussian) to 2.9x (a flat one) its median error; the same amplitudes in the
    layout that does not say so get radii nearly twice as wide (5.4x the median error: the
    old code's for both)."""
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    radii: dict[bool, list[float]] = {False: [], True: []}
    errors: dict[bool, list[float]] = {False: [], True: []}
    for truth, amplitudes in _draws(paper_room, sigma, 8, 25, 2031):
        for level, fingerprint in ((False, paper_fingerprint), (True, level_fingerprint)):
            solution = GridlessSolver(fingerprint, "correlation").solve_terminals(amplitudes)
            assert solution.covariances is not None
            radii[level] += list(confidence_radii(solution.covariances))
            errors[level] += list(np.linalg.norm(solution.positions - truth, axis=1))
    level_radii, level_errors = np.array(radii[True]), np.array(errors[True])
    # 200 terminals: a 95 % coverage lies in [0.90, 0.99] with overwhelming probability.
    assert 0.90 <= float(np.mean(level_errors <= level_radii)) <= 0.99
    assert float(np.median(level_radii) / np.median(level_errors)) < 3.5
    assert float(np.median(radii[False])) > 1.5 * float(np.median(level_radii))
    # Positions: the level fits never free a tilt, the others only when the data ask; in a
    # level room that changes little either way.
    assert float(np.mean(level_errors)) <= 1.02 * float(np.mean(errors[False]))


def test_aggregated_radii_of_a_level_room_hold_their_level(
    paper_room: Layout, paper_fingerprint: Fingerprint, level_fingerprint: Fingerprint
) -> None:
    """The aggregated correlation of four level terminals, 40 placements: the same
    estimates in both layouts once the undeclared room's joint fit holds its tilts level too
    (where a placement enters it, it would fit them: docs/decisions/tilts-after-tolerances.md),
    radii narrower where the layout says the photodiodes are level (the model-error variances
    are fitted together: without the tilt's, another's may grow a little), and those radii
    still cover about 95 %."""
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    inside: list[bool] = []
    narrower = 0
    ratios: list[float] = []
    for truth, amplitudes in _draws(paper_room, sigma, 4, 40, 2032):
        measurement = measurement_from_amplitudes(amplitudes, "correlation", paper_room.n_leds)
        plain = GridlessSolver(
            paper_fingerprint, "correlation", GridlessOptions(tolerance_tilt_sd=0.0)
        ).solve(measurement, 4)
        level = GridlessSolver(level_fingerprint, "correlation").solve(measurement, 4)
        assert plain.covariances is not None and level.covariances is not None
        np.testing.assert_array_equal(level.positions, plain.positions)
        level_radii = confidence_radii(level.covariances)
        plain_radii = confidence_radii(plain.covariances)
        ratios += list(level_radii / plain_radii)
        narrower += int(np.any(level_radii < 0.99 * plain_radii))
        distance = np.linalg.norm(truth[:, None, :] - level.positions[None, :, :], axis=2)
        rows, cols = linear_sum_assignment(distance)
        inside += list(distance[rows, cols] <= level_radii[cols])
    assert narrower >= 5  # the tilt's variance, fitted from noise, is gone where it was
    assert max(ratios) <= 1.05
    assert 0.88 <= float(np.mean(inside)) <= 1.0
