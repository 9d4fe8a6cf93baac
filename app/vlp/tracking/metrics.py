"""How good a set of tracks is against the truth: GOSPA and its parts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..typing import FloatArray

__all__ = ["Gospa", "gospa"]


@dataclass(frozen=True)
class Gospa:
    """The GOSPA distance (alpha = 2) and its parts, all in metres to the power ``p``
    before the root is taken on ``distance``.

    Attributes
    ----------
    distance : float
        ``(localisation + missed + false) ** (1 / p)``, metres.
    localisation : float
        Sum of ``d ** p`` over assigned pairs (each closer than the cut-off).
    missed : float
        ``c ** p / 2`` per true target left unassigned.
    false : float
        ``c ** p / 2`` per estimate left unassigned.
    """

    distance: float
    localisation: float
    missed: float
    false: float


def gospa(
    truth: FloatArray, estimates: FloatArray, *, cutoff_m: float = 1.0, p: float = 2.0
) -> Gospa:
    """GOSPA between true positions and estimates (Rahmathullah, Garcia-Fernandez and
    Svensson, FUSION 2017), alpha = 2.

    Parameters
    ----------
    truth : ndarray of shape (n, 2), metres
    estimates : ndarray of shape (m, 2), metres
    cutoff_m : float, default=1.0
        ``c``: pairs farther apart count as one missed and one false target.
    p : float, default=2.0

    Returns
    -------
    Gospa

    Examples
    --------
    >>> import numpy as np
    >>> round(gospa(np.array([[0.0, 0.0]]), np.array([[0.3, 0.4]])).distance, 6)
    0.5
    >>> gospa(np.array([[0.0, 0.0]]), np.zeros((0, 2))).missed
    0.5
    """
    truth = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    estimates = np.asarray(estimates, dtype=np.float64).reshape(-1, 2)
    half = cutoff_m**p / 2.0
    localisation, assigned = 0.0, 0
    if truth.shape[0] and estimates.shape[0]:
        distance = np.linalg.norm(truth[:, None, :] - estimates[None, :, :], axis=2)
        cost = np.minimum(distance, cutoff_m) ** p
        rows, cols = linear_sum_assignment(cost)
        close = distance[rows, cols] < cutoff_m
        localisation = float(np.sum(distance[rows, cols][close] ** p))
        assigned = int(np.count_nonzero(close))
    missed = half * (truth.shape[0] - assigned)
    false = half * (estimates.shape[0] - assigned)
    total = localisation + missed + false
    return Gospa(distance=total ** (1.0 / p), localisation=localisation, missed=missed, false=false)
