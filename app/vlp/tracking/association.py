"""Gated assignment of anonymous fixes to tracks of least total cost.

The cost of a pair is the negative log-likelihood of the fix under the track's two models,
each with its Mahalanobis distance and the log-determinant of its innovation covariance
(:func:`scipy.optimize.linear_sum_assignment` finds the assignment).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..typing import FloatArray, IntArray
from .bank import TrackBank
from .filter import combined, floored_covariances
from .settings import TrackerSettings

__all__ = ["INFEASIBLE", "assigned", "associate", "costs"]

# Cost of leaving a pair unassigned in the assignment matrix (beyond every gated cost).
INFEASIBLE = 1e12


def associate(
    predicted: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    settings: TrackerSettings,
    elapsed_s: FloatArray | None = None,
) -> tuple[IntArray, IntArray]:
    """Gated assignment of fixes to tracks of least total cost.

    Parameters
    ----------
    predicted : TrackBank
        ``n`` tracks predicted to the fixes' time.
    positions : ndarray of shape (m, 2), metres
    covariances : ndarray of shape (m, 2, 2), m^2
    settings : TrackerSettings
    elapsed_s : ndarray of shape (n,), seconds, default=None
        Time since each track's last update: a fix beyond the gate is still allowed where the
        terminal could have reached it at ``max_speed_mps`` (a start the prediction did not
        foresee); None: the gate alone.

    Returns
    -------
    track_rows, fix_rows : ndarray of shape (a,), int
        Pairs ``(track_rows[i], fix_rows[i])``; every pair is allowed.

    Notes
    -----
    The cost of a pair is ``-2 ln sum_k mu_k N(z; x_k, S_k)`` up to a constant: the negative
    log-likelihood of the fix under the track's mixture, each model ``k`` (probability
    ``mu_k``) with its own prediction ``x_k`` and ``S_k = P_k + R``, i.e. ``d2_k + ln det S_k``
    weighed across the models. One Gaussian in place of the mixture would be as wide as the
    two models apart: a standing track that may set off would claim a fix beside it as
    readily as a walking track that predicts the fix exactly. A pair is allowed where its
    squared Mahalanobis distance is within ``gate_chi2`` under some model or under the
    mixture taken as one Gaussian, or within reach (its larger cost makes the assignment
    prefer pairs within the gate).
    """
    if predicted.size == 0 or positions.shape[0] == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    cost = costs(predicted, positions, covariances, settings, elapsed_s)
    return assigned(cost)


def assigned(cost: FloatArray) -> tuple[IntArray, IntArray]:
    """The allowed pairs of the assignment of least total ``cost``."""
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] < INFEASIBLE
    return rows[keep].astype(np.intp), cols[keep].astype(np.intp)


def costs(
    predicted: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    settings: TrackerSettings,
    elapsed_s: FloatArray | None,
) -> FloatArray:
    """The cost ``(n, m)`` of each pair in :func:`associate` (:data:`INFEASIBLE`: not
    allowed)."""
    fix = floored_covariances(covariances, settings)
    # Each model's squared Mahalanobis distance and log-determinant, (n, models, m).
    distance2, log_det = _distances(
        predicted.means[:, :, :2], predicted.covariances[:, :, :2, :2], positions, fix
    )
    # The gate: on some model, or on the mixture as one Gaussian (wider than either where
    # the models disagree, as when a track may have set off).
    mean, covariance = combined(predicted)
    whole2, _ = _distances(mean[:, None, :2], covariance[:, None, :2, :2], positions, fix)
    allowed = np.minimum(np.min(distance2, axis=1), whole2[:, 0]) <= settings.gate_chi2
    if elapsed_s is not None:
        # Reach: how far the terminal can have gone, plus the 95 % spread of the fix.
        gap = np.hypot(
            positions[None, :, 0] - mean[:, None, 0], positions[None, :, 1] - mean[:, None, 1]
        )
        fix_spread = np.sqrt(np.trace(covariances, axis1=1, axis2=2))
        allowed |= gap <= settings.max_speed_mps * elapsed_s[:, None] + 2.448 * fix_spread[None, :]
    weight = np.log(np.maximum(predicted.model_probabilities, 1e-300))[:, :, None]
    log_likelihood = weight - 0.5 * (distance2 + log_det)
    return np.where(allowed, -2.0 * np.logaddexp.reduce(log_likelihood, axis=1), INFEASIBLE)


def _distances(
    means: FloatArray, covariances: FloatArray, positions: FloatArray, fixes: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Squared Mahalanobis distances and log-determinants ``(n, k, m)`` of ``m`` fixes
    (positions ``(m, 2)``, covariances ``(m, 2, 2)``) from ``n x k`` predictions (means
    ``(n, k, 2)``, covariances ``(n, k, 2, 2)``): ``S = P + R``, closed form for 2 x 2."""
    a = covariances[:, :, 0, 0, None] + fixes[None, None, :, 0, 0]
    b = covariances[:, :, 0, 1, None] + fixes[None, None, :, 0, 1]
    d = covariances[:, :, 1, 1, None] + fixes[None, None, :, 1, 1]
    nu0 = positions[None, None, :, 0] - means[:, :, 0, None]
    nu1 = positions[None, None, :, 1] - means[:, :, 1, None]
    det = a * d - b * b
    return (d * nu0 * nu0 - 2.0 * b * nu0 * nu1 + a * nu1 * nu1) / det, np.log(det)
