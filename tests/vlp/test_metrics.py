"""Metrics: optimal matching, invariances, known values."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.errors import MeasurementError
from app.vlp.metrics import (
    match_positions,
    matched_errors,
    mean_position_error,
    support_recovery_rate,
)


def _brute_force(estimates: np.ndarray, truth: np.ndarray) -> float:
    """Smallest mean distance over every injective pairing (independent of Hungarian)."""
    k = min(len(estimates), len(truth))
    best = np.inf
    for est_rows in itertools.permutations(range(len(estimates)), k):
        for true_rows in itertools.combinations(range(len(truth)), k):
            mean = np.mean(
                np.linalg.norm(estimates[list(est_rows)] - truth[list(true_rows)], axis=1)
            )
            best = min(best, float(mean))
    return best


def test_known_value() -> None:
    truth = np.array([[0.0, 0.0], [3.0, 4.0]])
    estimates = np.array([[3.0, 4.0], [0.0, 0.5]])
    assert mean_position_error(estimates, truth) == pytest.approx(0.25)
    assert_allclose(matched_errors(estimates, truth), [0.5, 0.0])
    est_idx, true_idx = match_positions(estimates, truth)
    assert_array_equal(est_idx, [1, 0])
    assert_array_equal(true_idx, [0, 1])


@pytest.mark.parametrize("seed", range(10))
def test_against_brute_force_and_invariances(seed: int) -> None:
    gen = np.random.default_rng(seed)
    n_est, n_true = gen.integers(1, 6, size=2)
    estimates = gen.uniform(0, 4, size=(n_est, 2))
    truth = gen.uniform(0, 4, size=(n_true, 2))
    error = mean_position_error(estimates, truth)
    assert error >= 0
    assert error == pytest.approx(_brute_force(estimates, truth), rel=1e-12)
    assert matched_errors(estimates, truth).shape == (min(n_est, n_true),)
    assert mean_position_error(estimates[gen.permutation(n_est)], truth) == pytest.approx(error)
    assert mean_position_error(estimates, truth[gen.permutation(n_true)]) == pytest.approx(error)
    assert mean_position_error(truth, estimates) == pytest.approx(error)  # symmetric
    assert mean_position_error(truth, truth) == 0.0


def test_different_counts_match_the_best_subset() -> None:
    truth = np.array([[1.0, 1.0], [3.0, 3.0]])
    estimates = np.array([[3.1, 3.0], [1.0, 1.2], [0.0, 4.0]])  # one surplus estimate
    assert mean_position_error(estimates, truth) == pytest.approx(0.15)
    assert mean_position_error(estimates[:1], truth) == pytest.approx(0.1)


@pytest.mark.parametrize(
    "bad",
    [np.zeros((0, 2)), np.zeros((3,)), np.zeros((2, 3)), np.array([[np.nan, 0.0]])],
    ids=["empty", "flat", "three-columns", "nan"],
)
def test_bad_inputs(bad: np.ndarray) -> None:
    with pytest.raises(MeasurementError):
        mean_position_error(bad, np.zeros((1, 2)))


def test_support_recovery_rate() -> None:
    assert support_recovery_rate(np.array([4, 7, 9]), np.array([7, 4, 2, 1])) == 0.5
    assert support_recovery_rate(np.array([1, 2]), np.array([2, 1])) == 1.0
    assert support_recovery_rate(np.array([], dtype=int), np.array([3])) == 0.0
    with pytest.raises(MeasurementError):
        support_recovery_rate(np.array([1]), np.array([], dtype=int))
