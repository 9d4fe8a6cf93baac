"""Other optima: positions that another position mimics, and confidence regions that hold them.

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

:func:`far_optima` looks for any other optimum of one terminal's own amplitudes over the
grid (a receiver in the dark receives noise, which every dark spot explains as well), for
the same widening; :func:`farthest_in_region` is its region, shared with the aggregated
forms' scan (each estimate moved over the grid with the others held,
``GridlessSolver._aggregated_far_optima``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .typing import FloatArray, IntArray

__all__ = [
    "OFF_LINE_FRACTION",
    "TWIN_MAX_CHANGE",
    "covering_twins",
    "far_optima",
    "farthest_in_region",
    "mirror_twins",
    "reaching_beyond",
    "twins_possible",
]

# Gains within this relative change are taken as the same: the LEDs' own tolerances (5 % in
# amplitude, the solver's prior) make a real room differ from its model by as much.
TWIN_MAX_CHANGE = 0.05
# An LED is "seen" where its gain is at least this fraction of the strongest one's (with
# reflections in the model every LED gives a little everywhere).
_SEEN_FRACTION = 0.01
# LEDs count as on one line while their rms distance from it is at most this fraction of
# the estimate's (a square array's LEDs are not, near its axes of symmetry or anywhere).
OFF_LINE_FRACTION = 0.25
# The 95 % quantile of chi-square with 2 degrees of freedom: far_optima's region, and the
# 95 % circle of an isotropic unit Gaussian, sqrt of it.
_REGION_CHI2 = 5.991464547107979
_CIRCLE_95 = math.sqrt(_REGION_CHI2)
# twins_possible: a room where no grid point has a twin under these looser limits has none
# between grid points either (the limits change slowly over a cell).
_LOOSER = 2.0


def mirror_twins(
    positions: FloatArray,
    led_xy: FloatArray,
    gains: Callable[[FloatArray], FloatArray],
    room_size: tuple[float, float],
    max_change: float = TWIN_MAX_CHANGE,
    off_line_fraction: float = OFF_LINE_FRACTION,
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
    off_line_fraction : float, default=OFF_LINE_FRACTION
        Largest rms distance of the seen LEDs from their line, as a fraction of the
        estimate's distance from it.

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
    own = np.asarray(gains(points), dtype=np.float64)  # (M, K)
    strongest = own.max(axis=0, initial=0.0)
    seen = (own >= _SEEN_FRACTION * strongest) & (strongest > 0.0)  # (M, K)
    count = seen.sum(axis=0).astype(np.float64)
    # Each estimate's seen LEDs: their centre and 2 x 2 scatter, all estimates at once.
    share = seen / np.maximum(count, 1.0)
    centre = share.T @ leds  # (K, 2)
    xx = share.T @ (leds[:, 0] ** 2) - centre[:, 0] ** 2
    yy = share.T @ (leds[:, 1] ** 2) - centre[:, 1] ** 2
    xy = share.T @ (leds[:, 0] * leds[:, 1]) - centre[:, 0] * centre[:, 1]
    # The principal axis (the line that fits them best) and the mean square off it.
    half_gap = np.hypot(0.5 * (xx - yy), xy)
    off_line = np.maximum(0.5 * (xx + yy) - half_gap, 0.0)
    angle = 0.5 * np.arctan2(2.0 * xy, xx - yy)
    direction = np.column_stack((np.cos(angle), np.sin(angle)))
    offset = points - centre
    along = np.sum(offset * direction, axis=1)
    across = np.abs(offset[:, 0] * direction[:, 1] - offset[:, 1] * direction[:, 0])
    mirrored = centre + 2.0 * along[:, np.newaxis] * direction - offset
    length, width = room_size
    # Two or more LEDs seen (one gives a ring, which the covariance already leaves open),
    # near one line compared with the estimate's distance from it, and the image in the
    # room; whether near enough, the gains at the image decide.
    candidate = (
        (count >= 2)
        & (across > 0.0)
        & (np.sqrt(off_line) <= off_line_fraction * across)
        & (mirrored[:, 0] >= 0.0)
        & (mirrored[:, 0] <= length)
        & (mirrored[:, 1] >= 0.0)
        & (mirrored[:, 1] <= width)
    )
    candidates = np.where(candidate[:, np.newaxis], mirrored, np.nan)
    found = np.flatnonzero(np.isfinite(candidates[:, 0]))
    if found.size == 0:
        return twins
    other = np.asarray(gains(candidates[found]), dtype=np.float64)
    change = np.linalg.norm(other - own[:, found], axis=0)
    size = np.linalg.norm(own[:, found], axis=0)
    same = change <= max_change * size
    twins[found[same]] = candidates[found[same]]
    return twins


def twins_possible(
    grid_points: FloatArray,
    led_xy: FloatArray,
    gains: Callable[[FloatArray], FloatArray],
    room_size: tuple[float, float],
) -> bool:
    """Whether any of ``grid_points`` (N, 2) has a mirror twin under limits twice as loose
    as :func:`mirror_twins`'s: where none has, no estimate needs the check (a 4 x 4 array of
    wide beams: every receiver sees LEDs off any one line). Parameters as there."""
    twins = mirror_twins(
        grid_points,
        led_xy,
        gains,
        room_size,
        max_change=_LOOSER * TWIN_MAX_CHANGE,
        off_line_fraction=_LOOSER * OFF_LINE_FRACTION,
    )
    return bool(np.isfinite(twins[:, 0]).any())


def far_optima(
    amplitudes: FloatArray,
    gains: FloatArray,
    grid_points: FloatArray,
    positions: FloatArray,
    covariances: FloatArray,
    noise_variance: float,
    spacing: float,
    column_energy: FloatArray | None = None,
    gain_sd: float | None = None,
) -> FloatArray:
    """For terminals fitted from their own amplitudes: the farthest grid point that explains
    a terminal's amplitudes about as well as its estimate, where it lies beyond the
    estimate's 95 % circle (another optimum the covariance does not know of); NaN where none.

    The profile over the grid of each terminal's cost with its gain free (least squares,
    non-negative), ``c_j = ||y||^2 - max(g_j . y, 0)^2 / ||g_j||^2`` in units of the noise
    variance, and its region ``c_j - min c <= 5.99`` (the 95 % quantile of chi-square with
    2 degrees of freedom): the grid's version of a likelihood-ratio confidence region
    (:func:`farthest_in_region`). Points of it within the circle plus 1.5 grid steps are the
    estimate's own neighbourhood. With ``gain_sd`` the gain ``a`` has the fit's prior
    ``N(1, gain_sd^2)`` (the log gain's, to first order): ``c_j = min_a ||y - a g_j||^2 +
    lam (a - 1)^2`` with ``lam = noise_variance / gain_sd^2``, that is ``||y||^2 + lam -
    (g_j . y + lam)^2 / (||g_j||^2 + lam)``; a place that explains the amplitudes only with
    a gain the fit would not take is not another optimum.

    Parameters
    ----------
    amplitudes : ndarray of shape (K, M)
        Each terminal's amplitudes, in the units of ``gains``.
    gains : ndarray of shape (M, N)
        The channel gains at every grid point.
    grid_points : ndarray of shape (N, 2), metres
    positions : ndarray of shape (K, 2), metres
    covariances : ndarray of shape (K, 2, 2), m^2
        Each estimate's covariance so far (non-finite: nothing is far).
    noise_variance : float
        Variance of one amplitude's noise, in the units of ``gains`` squared.
    spacing : float, metres
        The grid step.
    column_energy : ndarray of shape (N,) or None
        ``||g_j||^2`` of every grid point, when already known (else computed).
    gain_sd : float or None
        The standard deviation of the fit's prior on each terminal's gain (None: free).

    Returns
    -------
    far : ndarray of shape (K, 2), metres; NaN rows where the region stays near the estimate
    """
    values = np.asarray(amplitudes, dtype=np.float64)
    if not noise_variance > 0.0:
        return np.full((values.shape[0], 2), np.nan)
    if column_energy is None:
        column_energy = np.einsum("mn,mn->n", gains, gains)
    norms = np.maximum(column_energy, 1e-300)
    # c_j - min c = (max explained - explained_j) / sigma^2
    if gain_sd is None:
        explained = np.maximum(values @ gains, 0.0) ** 2 / norms / noise_variance  # (K, N)
    else:
        lam = noise_variance / gain_sd**2
        explained = ((values @ gains + lam) ** 2 / (norms + lam) - lam) / noise_variance
    return farthest_in_region(
        explained, explained.max(axis=1), grid_points, positions, covariances, spacing
    )


def farthest_in_region(
    explained: FloatArray,
    best: FloatArray,
    grid_points: FloatArray,
    positions: FloatArray,
    covariances: FloatArray,
    spacing: float,
) -> FloatArray:
    """Per estimate, the farthest grid point of its profile's 95 % region where it lies
    beyond the estimate's 95 % circle plus 1.5 grid steps; NaN where none.

    The region is the grid's likelihood-ratio region: the points where the estimate's cost,
    minimised over its gain with everything else held, is within the 95 % quantile of
    chi-square with 2 degrees of freedom (5.99) of its minimum. The circle is bounded from
    above by that of the covariance's larger axis (``2.45 sqrt(lambda_max)``): no exact
    radius needed, and no point within the true circle counts as far.

    Parameters
    ----------
    explained : ndarray of shape (K, N)
        How much of its cost each estimate would explain at each grid point, in units of
        the noise variance (the cost's decrease there).
    best : ndarray of shape (K,)
        The most any placement explains (at least ``explained.max(axis=1)``).
    grid_points : ndarray of shape (N, 2), metres
    positions : ndarray of shape (K, 2), metres
    covariances : ndarray of shape (K, 2, 2), m^2
        Each estimate's covariance so far (non-finite: nothing is far).
    spacing : float, metres
        The grid step.

    Returns
    -------
    far : ndarray of shape (K, 2), metres; NaN rows where the region stays near the estimate
    """
    far = np.full((explained.shape[0], 2), np.nan)
    # The region is a few grid points per estimate: distances to those only, and the
    # circles only of the estimates whose region reaches beyond their neighbourhood.
    rows, cols, distance = _region(explained, best, grid_points, positions)
    if distance.size == 0 or distance.max() <= 1.5 * spacing:
        return far  # the common case: every region stays in its neighbourhood
    reach = np.full(explained.shape[0], -np.inf)
    np.maximum.at(reach, rows, distance)
    for k in np.flatnonzero(reach > 1.5 * spacing):
        # Python floats: a non-finite covariance gives nan or inf here without a warning.
        xx, xy, yx, yy = (float(v) for v in np.ravel(covariances[k]))
        larger = 0.5 * (xx + yy) + math.hypot(0.5 * (xx - yy), 0.5 * (xy + yx))
        radius = _CIRCLE_95 * math.sqrt(abs(larger)) if math.isfinite(larger) else math.inf
        if reach[k] <= radius + 1.5 * spacing:
            continue
        mine = rows == k
        far[k] = grid_points[cols[mine][np.argmax(distance[mine])]]
    return far


def reaching_beyond(
    explained: FloatArray,
    best: FloatArray,
    grid_points: FloatArray,
    positions: FloatArray,
    distance: float,
) -> IntArray:
    """The estimates whose profile's 95 % region (as :func:`farthest_in_region`'s) holds a
    grid point more than ``distance`` (metres) from them, ascending.

    Parameters
    ----------
    explained : ndarray of shape (K, N)
    best : ndarray of shape (K,)
        As :func:`farthest_in_region`'s.
    grid_points : ndarray of shape (N, 2), metres
    positions : ndarray of shape (K, 2), metres
    distance : float, metres

    Returns
    -------
    estimates : ndarray of shape (n,), int
    """
    rows, _, reach = _region(explained, best, grid_points, positions)
    return np.unique(rows[reach > distance]).astype(np.int64)


def _region(
    explained: FloatArray, best: FloatArray, grid_points: FloatArray, positions: FloatArray
) -> tuple[IntArray, IntArray, FloatArray]:
    """The profiles' 95 % regions as (estimate, grid point) pairs, each with the point's
    distance from its estimate (metres): the points where an estimate's profile is within
    chi-square(2)'s 95 % quantile of its best."""
    rows, cols = np.nonzero(explained >= np.asarray(best)[:, np.newaxis] - _REGION_CHI2)
    points = np.asarray(positions)[rows]
    distance = np.hypot(grid_points[cols, 0] - points[:, 0], grid_points[cols, 1] - points[:, 1])
    return rows, cols, distance


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
