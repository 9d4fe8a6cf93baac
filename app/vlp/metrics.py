"""Accuracy metrics: position errors under the best matching, and support recovery.

Estimates come unordered, so they are matched to the true targets by the assignment that
minimises the total distance (Hungarian algorithm), and the paper's average positioning
error (eq. 18) is the mean distance over the matched pairs.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from .errors import MeasurementError
from .typing import FloatArray, IntArray

__all__ = [
    "match_positions",
    "matched_errors",
    "mean_position_error",
    "support_recovery_rate",
]


def _as_points(points: object, field: str) -> FloatArray:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise MeasurementError(f"{field} must have shape (K, 2), got {array.shape}", field=field)
    if not np.all(np.isfinite(array)):
        raise MeasurementError(f"{field} contains NaN or infinite values", field=field)
    return array


def match_positions(estimates: FloatArray, truth: FloatArray) -> tuple[IntArray, IntArray]:
    """The pairing of estimates with true targets of least total distance.

    Parameters
    ----------
    estimates : ndarray of shape (K_est, 2)
        Estimated ``(x, y)``, metres.
    truth : ndarray of shape (K_true, 2)
        True ``(x, y)``, metres.

    Returns
    -------
    estimate_indices, truth_indices : ndarray of shape (min(K_est, K_true),)
        Pair ``n`` matches ``estimates[estimate_indices[n]]`` with
        ``truth[truth_indices[n]]``; sorted by ``truth_indices`` when ``K_est >= K_true``.

    Raises
    ------
    MeasurementError
        When an input is not of shape (K, 2) or not finite.

    Examples
    --------
    >>> match_positions(np.array([[3.0, 3.0], [0.0, 0.0]]), np.array([[0.1, 0.0], [3.0, 2.9]]))
    (array([1, 0]), array([0, 1]))
    """
    est = _as_points(estimates, "estimates")
    true = _as_points(truth, "truth")
    distances = np.linalg.norm(true[:, None, :] - est[None, :, :], axis=2)  # (K_true, K_est)
    truth_indices, estimate_indices = linear_sum_assignment(distances)
    return (np.asarray(estimate_indices, dtype=np.intp), np.asarray(truth_indices, dtype=np.intp))


def matched_errors(estimates: FloatArray, truth: FloatArray) -> FloatArray:
    """Distances between matched estimates and true targets.

    Parameters
    ----------
    estimates : ndarray of shape (K_est, 2)
        Metres.
    truth : ndarray of shape (K_true, 2)
        Metres.

    Returns
    -------
    errors : ndarray of shape (min(K_est, K_true),)
        Metres, in the order of :func:`match_positions`. When the counts differ, only
        ``min(K_est, K_true)`` pairs are formed (the best-matching ones); surplus estimates
        or missed targets are not counted here.

    Examples
    --------
    >>> matched_errors(np.array([[3.0, 3.0], [0.0, 0.0]]), np.array([[0.0, 0.4], [3.0, 3.0]]))
    array([0.4, 0. ])
    """
    est_idx, true_idx = match_positions(estimates, truth)
    est = np.asarray(estimates, dtype=np.float64)
    true = np.asarray(truth, dtype=np.float64)
    return np.asarray(np.linalg.norm(est[est_idx] - true[true_idx], axis=1))


def mean_position_error(estimates: FloatArray, truth: FloatArray) -> float:
    """The paper's average positioning error under the optimal matching (eq. 18).

    Parameters
    ----------
    estimates : ndarray of shape (K_est, 2)
        Metres.
    truth : ndarray of shape (K_true, 2)
        Metres.

    Returns
    -------
    error : float
        ``(1/K) sum_k ||p_k - p_hat_pi(k)||`` in metres, minimised over matchings ``pi``,
        with ``K = min(K_est, K_true)`` (see :func:`matched_errors`).

    Raises
    ------
    MeasurementError
        When either set is empty or malformed.

    Examples
    --------
    >>> mean_position_error(np.array([[3.0, 3.0], [0.0, 0.0]]),
    ...                     np.array([[0.0, 0.4], [3.0, 3.0]]))
    0.2
    """
    errors = matched_errors(estimates, truth)
    if errors.size == 0:
        raise MeasurementError(
            "need at least one estimate and one true position", field="estimates"
        )
    return float(np.mean(errors))


def support_recovery_rate(estimated_indices: IntArray, true_indices: IntArray) -> float:
    """Fraction of the true grid points that are among the estimated ones.

    Parameters
    ----------
    estimated_indices : ndarray of shape (K_est,)
        Estimated grid columns.
    true_indices : ndarray of shape (K_true,)
        True grid columns (at least one).

    Returns
    -------
    rate : float
        ``|set(estimated) & set(true)| / |set(true)|``, in [0, 1].

    Examples
    --------
    >>> support_recovery_rate(np.array([4, 7, 9]), np.array([7, 4, 2, 1]))
    0.5
    """
    true = set(np.asarray(true_indices).ravel().tolist())
    if not true:
        raise MeasurementError("need at least one true grid index", field="true_indices")
    found = set(np.asarray(estimated_indices).ravel().tolist())
    return len(found & true) / len(true)
