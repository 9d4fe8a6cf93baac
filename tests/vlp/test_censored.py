"""LEDs not detected: censored below the terminal's floor (solvers/_censored.py)."""

from __future__ import annotations

import numpy as np

from app.vlp.fingerprints import Fingerprint
from app.vlp.layout import Layout
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers._censored import (
    censored_substitutes,
    detection_floors,
    with_censored_variance,
)
from app.vlp.solvers.gridless import GridlessSolver


def test_the_floor_is_the_terminals_own_or_its_weakest_detected_amplitude() -> None:
    nan = np.nan
    amplitudes = np.array([[3.0, nan, 1.5, 4.0], [nan, 2.0, 5.0, nan]])
    np.testing.assert_allclose(detection_floors(amplitudes, None), [1.5, 2.0])
    np.testing.assert_allclose(detection_floors(amplitudes, np.array([0.6, nan])), [0.6, 2.0])
    filled, extra = censored_substitutes(amplitudes, np.array([0.6, nan]))
    # Uniform below the floor: mean f / 2, variance f^2 / 12.
    np.testing.assert_allclose(filled, [[3.0, 0.3, 1.5, 4.0], [1.0, 2.0, 5.0, 1.0]])
    np.testing.assert_allclose(extra, [[0, 0.36 / 12, 0, 0], [4 / 12, 0, 0, 4 / 12]])
    detected = np.ones((1, 3))
    assert censored_substitutes(detected)[1].sum() == 0
    assert with_censored_variance(0.25, np.zeros(3)) == 0.25
    widened = with_censored_variance(0.25, np.array([0, 1.0, 0]))
    np.testing.assert_allclose(widened, [0.25, 1.25, 0.25])


def test_undetected_leds_sent_as_null_beat_the_floor_sent_as_a_number(
    paper_room: Layout, paper_fingerprint: Fingerprint
) -> None:
    # Terminals near a corner: the far LEDs fall below a floor at a fifth of the brightest
    # amplitude. Sent as the floor (what a client without "null" does), the fit believes
    # those LEDs are that bright; censored, it only knows they are weaker.
    solver = GridlessSolver(paper_fingerprint, "correlation")
    truth = np.array([[0.35, 0.4], [3.6, 0.3], [0.5, 3.7], [3.4, 3.5], [1.9, 0.3]])
    clean = true_amplitudes(paper_room, truth)
    rng = np.random.default_rng(5)
    noisy = clean * np.exp(0.03 * rng.standard_normal(clean.shape))
    floor = 0.2 * noisy.max(axis=1, keepdims=True)
    below = noisy < floor
    assert below.sum(axis=1).min() >= 6
    censored = np.where(below, np.nan, noisy)
    at_floor = np.where(below, floor, noisy)
    floors = floor[:, 0]
    null_errors = np.linalg.norm(
        solver.solve_terminals(censored, floors=floors).positions - truth, axis=1
    )
    floor_errors = np.linalg.norm(solver.solve_terminals(at_floor).positions - truth, axis=1)
    assert np.mean(null_errors) < 0.05
    assert np.mean(null_errors) < 0.5 * np.mean(floor_errors)
