"""Mirror twins: positions that another position mimics, and confidence regions that say so.

A receiver that sees LEDs lying on one line (a corridor with a single row of lights, a room
with two LEDs, or the two or three LEDs of a row that a receiver near a wall sees) gets the
same line-of-sight gains at its mirror image across that line: the same distances, the same
angles. No fit can tell the two apart, and the covariance of a fit (its curvature at one of
the two optima) does not know about the other. Such an estimate's 95 % region must hold
both.

:func:`mirror_twins` finds, per estimate, the mirror image across the line of the LEDs it
sees, and keeps it where its gains are within ``max_change`` of the estimate's (the same
LEDs seen, reflections and beams aside); :func:`covering_twins` widens each covariance to
hold both. Both are plain NumPy: a few channel evaluations per answer.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .typing import FloatArray

__all__ = ["TWIN_MAX_CHANGE", "covering_twins", "mirror_twins"]

# Gains within this relative change are taken as the same: the LEDs' own tolerances (5 % in
# amplitude, the solver's prior) make a real room differ from its model by as much.
TWIN_MAX_CHANGE = 0.05
# An LED is "seen" where its gain is at least this fraction of the strongest one's (with
# reflections in the model every LED gives a little everywhere).
_SEEN_FRACTION = 0.01
# LEDs count as on one line while their rms distance from it is at most this fraction of
# the estimate's (a square array's LEDs are not, near its axes of symmetry or anywhere).
_OFF_LINE_FRACTION = 0.25


def mirror_twins(
    positions: FloatArray,
    led_xy: FloatArray,
    gains: Callable[[FloatArray], FloatArray],
    room_size: tuple[float, float],
    max_change: float = TWIN_MAX_CHANGE,
) -> FloatArray:
    """Each estimate's mirror twin, or NaN where it has none.

    Parameters
    ----------
    positions : ndarray of shape (K, 2), metres
        The estimates.
    led_xy : ndarray of shape (M, 2), metres
        The LEDs' floor-plan positions.
    gains : callable
        ``gains(points)`` with points of shape (P, 2) returns the channel gains, shape
        (M, P), of a receiver at each point (any common unit).
    room_size : (length, width), metres
        A twin must lie in ``[0, length] x [0, width]``.
    max_change : float, default=TWIN_MAX_CHANGE
        Largest ``||g(twin) - g(p)|| / ||g(p)||`` of a twin.

    Returns
    -------
    twins : ndarray of shape (K, 2), metres; NaN rows where the estimate has no twin
        (it sees fewer than two LEDs, or LEDs not on one line, or its mirror image is
        outside the room or receives other gains).
    """
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    leds = np.asarray(led_xy, dtype=np.float64).reshape(-1, 2)
    twins = np.full_like(points, np.nan)
    if points.shape[0] == 0:
        return twins
    own = np.asarray(gains(points), dtype=np.float64)
    candidates = np.full_like(points, np.nan)
    for k, point in enumerate(points):
        column = own[:, k]
        strongest = float(column.max(initial=0.0))
        if not strongest > 0.0:
            continue
        seen = leds[column >= _SEEN_FRACTION * strongest]
        if seen.shape[0] < 2:
            continue  # one LED: a ring, which the covariance already leaves open
        centre = seen.mean(axis=0)
        # The line that fits the seen LEDs best (their principal axis), if they lie near it
        # compared with the estimate's distance from it; whether near enough, the gains at
        # the mirror image decide.
        _, spreads, axes = np.linalg.svd(seen - centre, full_matrices=False)
        direction = axes[0]
        offset = point - centre
        across = abs(offset @ axes[1]) if axes.shape[0] > 1 else 0.0
        rms_off_line = spreads[1] / np.sqrt(seen.shape[0]) if spreads.shape[0] > 1 else 0.0
        if rms_off_line > _OFF_LINE_FRACTION * across:
            continue
        mirrored = centre + 2.0 * (offset @ direction) * direction - offset
        length, width = room_size
        if 0.0 <= mirrored[0] <= length and 0.0 <= mirrored[1] <= width:
            candidates[k] = mirrored
    found = np.flatnonzero(np.isfinite(candidates[:, 0]))
    if found.size == 0:
        return twins
    other = np.asarray(gains(candidates[found]), dtype=np.float64)
    change = np.linalg.norm(other - own[:, found], axis=0)
    size = np.linalg.norm(own[:, found], axis=0)
    same = change <= max_change * size
    twins[found[same]] = candidates[found[same]]
    return twins


def covering_twins(covariances: FloatArray, positions: FloatArray, twins: FloatArray) -> FloatArray:
    """Covariances widened to hold each estimate's twin: ``C + d d^T / 2`` with ``d`` the
    step to the twin. The even mixture of the two points has ``C + d d^T / 4``, whose 95 %
    circle around the estimate is only ``0.98 |d|`` wide when ``C`` is small; with half of
    ``d d^T`` it is ``1.39 |d|``, which holds the twin and its neighbourhood.

    Parameters
    ----------
    covariances : ndarray of shape (K, 2, 2), m^2
    positions, twins : ndarrays of shape (K, 2), metres (twins NaN where none)

    Returns
    -------
    widened : ndarray of shape (K, 2, 2), m^2 (a copy; rows without a twin unchanged)
    """
    widened = np.array(covariances, dtype=np.float64)
    steps = np.asarray(twins, dtype=np.float64) - np.asarray(positions, dtype=np.float64)
    has = np.isfinite(steps).all(axis=1)
    widened[has] += 0.5 * steps[has, :, np.newaxis] * steps[has, np.newaxis, :]
    return widened
