"""95 % confidence radii of 2-D position covariances, and covariances bounded to what a
room can show.

An answer's ``accuracy_m`` is the radius of the circle around the estimate that holds the
truth with probability ``level`` under its Gaussian covariance (not the ellipse's semi-axis):
the radial probability is integrated by Gauss-Legendre quadrature and solved by Newton's
method, in one compiled call for a batch (:mod:`app.vlp._radii_compiled`) with this module's
NumPy reference.
"""

from __future__ import annotations

import functools
import math
from typing import cast

import numpy as np
from scipy import special

from .typing import FloatArray

__all__ = [
    "bounded_covariances",
    "confidence_radii",
    "confidence_radius",
    "covariance_radii_kernel",
    "covariance_radii_reference",
]

# Gauss-Legendre nodes and weights on [-pi/2, pi/2] for the radial probability below.
_NODES, _UNIT_WEIGHTS = np.polynomial.legendre.leggauss(96)
_ANGLES = 0.5 * math.pi * _NODES
_WEIGHTS = 0.5 * math.pi * _UNIT_WEIGHTS
_SINES = np.sin(_ANGLES)
_COSINES = np.cos(_ANGLES)
_ROOT_TWO_PI = math.sqrt(2.0 * math.pi)
# Newton on the radial probability: stop when it is this close to the level (a radius to
# ~1e-13 relative); the bracket bounds the steps whatever happens.
_RADIUS_TOLERANCE = 1e-14
# A 2 x 2 covariance is taken as one while its determinant is above this times its trace
# squared (about the ratio of its eigenvalues: standard deviations 1e6 apart). Below it
# a direction had no information: a pseudo-inverse gives it 0, not infinity (a receiver
# that sees one LED lies on a ring around it, and the ring's tangent came out "exact").
_MIN_EIGENVALUE_RATIO = 1e-12
_MAX_RADIUS_STEPS = 60


def confidence_radius(covariance: FloatArray, level: float = 0.95) -> float:
    """Radius of the circle around the estimate that holds the truth with ``level``.

    One covariance; see :func:`confidence_radii` for the method.

    Parameters
    ----------
    covariance : ndarray of shape (2, 2), m^2
    level : float, default=0.95

    Returns
    -------
    radius : float, metres

    Examples
    --------
    >>> round(confidence_radius(np.eye(2) * 0.01), 4)  # sqrt(-2 ln 0.05) * 0.1
    0.2448
    """
    covariance = np.asarray(covariance, dtype=np.float64)
    return float(confidence_radii(covariance[np.newaxis], level)[0])


def confidence_radii(covariances: FloatArray, level: float = 0.95) -> FloatArray:
    """Radii of the circles around the estimates that hold the truth with ``level``.

    For a zero-mean 2-D Gaussian error with covariance eigenvalues ``l1 >= l2``,
    ``|e|^2 = l1 X^2 + l2 Y^2`` with X, Y independent standard normals. With ``r = sqrt(l1) u``,
    ``rho = l2 / l1`` and ``X = u sin(t)``:
    ``P(|e| <= r) = int_{-pi/2}^{pi/2} phi(u sin t) (2 Phi(u cos(t) / sqrt(rho)) - 1) u cos(t) dt``
    (Gauss-Legendre). All estimates are solved together for ``u`` by Newton's method on that
    quadrature, with its exact derivative, kept inside a shrinking bracket (bisection when a
    step leaves it). An answer asks for one radius per estimate, so this runs on every
    localize request.

    Parameters
    ----------
    covariances : ndarray of shape (K, 2, 2), m^2
    level : float, default=0.95

    Returns
    -------
    radii : ndarray of shape (K,), metres (inf for a non-finite covariance, 0 for a zero one)
    """
    cov = np.asarray(covariances, dtype=np.float64)
    if cov.ndim != 3 or cov.shape[1:] != (2, 2):
        raise ValueError(f"covariances must have shape (K, 2, 2), got {cov.shape}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if cov.shape[0] == 0:
        return np.zeros(0)
    # The kernel engine is imported here, not at the top: numba loads with the first
    # radius, not with this module.
    from ._kernels import dispatch

    # P(0) = 0 < level and P(two_d) >= level (rho <= 1): a bracket for every estimate.
    one_d, two_d = _radial_bracket(float(level))
    return dispatch(covariance_radii_kernel, covariance_radii_reference)(
        cov, float(level), one_d, two_d
    )


@functools.lru_cache(maxsize=8)
def _radial_bracket(level: float) -> tuple[float, float]:
    """``u`` of the ``level`` radius when ``rho -> 0`` and when ``rho = 1`` (Rayleigh): the
    bounds of every estimate's root (:func:`covariance_radii_reference`)."""
    return float(special.ndtri(0.5 + 0.5 * level)), math.sqrt(-2.0 * math.log1p(-level))


def covariance_radii_kernel(
    covariances: FloatArray, level: float, one_d: float, two_d: float
) -> FloatArray:
    """:func:`covariance_radii_reference` compiled (:mod:`app.vlp._radii_compiled`: one
    call per answer; each estimate's eigenvalues in closed form, as LAPACK's for a 2 x 2
    matrix, and its own Newton iteration to the tolerance)."""
    from . import _radii_compiled

    return cast(
        "FloatArray",
        _radii_compiled.covariance_radii_kernel(
            np.ascontiguousarray(covariances, dtype=np.float64),
            level,
            one_d,
            two_d,
            (_WEIGHTS, _SINES, _COSINES),
            _RADIUS_TOLERANCE,
            _MAX_RADIUS_STEPS,
        ),
    )


def covariance_radii_reference(
    covariances: FloatArray, level: float, one_d: float, two_d: float
) -> FloatArray:
    """:func:`confidence_radii` of validated covariances (K, 2, 2), K >= 1, in NumPy: each
    symmetrised covariance's eigenvalues ``l2 <= l1``, then ``u`` per estimate with
    ``P(|e| <= u sqrt(l1)) = level`` for ``rho = l2 / l1`` by Newton's method kept inside
    the bracket ``[0, two_d]``, from between the one- and two-dimensional roots
    (``one_d``, ``two_d``), on the radial probability by Gauss-Legendre quadrature."""
    finite = np.all(np.isfinite(covariances), axis=(1, 2))
    radii = np.where(finite, 0.0, math.inf)
    eigen = np.zeros((covariances.shape[0], 2))
    kept = covariances[finite]
    eigen[finite] = np.linalg.eigvalsh(0.5 * (kept + kept.transpose(0, 2, 1)))
    major = eigen[:, 1]
    solve = finite & (major > 0.0)
    if not np.any(solve):
        return radii
    major = major[solve]
    root_ratio = np.sqrt(np.maximum(eigen[solve, 0] / major, 1e-300))
    ratio = root_ratio[:, np.newaxis]
    low = np.zeros(root_ratio.size)
    high = np.full(root_ratio.size, two_d * 1.01)
    reach = one_d + (two_d - one_d) * root_ratio  # within a few % of the root
    for _ in range(_MAX_RADIUS_STEPS):
        u = reach[:, np.newaxis]
        along = u * _SINES
        across = u * _COSINES / ratio
        density = np.exp(-0.5 * along**2) / _ROOT_TWO_PI
        inner = 2.0 * special.ndtr(across) - 1.0
        excess = np.sum(_WEIGHTS * density * inner * u * _COSINES, axis=1) - level
        slope = np.sum(
            _WEIGHTS
            * _COSINES
            * density
            * (
                (1.0 - along**2) * inner
                + u * (2.0 / _ROOT_TWO_PI) * np.exp(-0.5 * across**2) * _COSINES / ratio
            ),
            axis=1,
        )
        if np.all(np.abs(excess) <= _RADIUS_TOLERANCE):
            break
        low = np.where(excess < 0.0, reach, low)
        high = np.where(excess > 0.0, reach, high)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = reach - excess / slope
        inside = (slope > 0.0) & (step > low) & (step < high)
        reach = np.where(inside, step, 0.5 * (low + high))
    radii[solve] = np.sqrt(major) * reach
    return radii


def bounded_covariances(
    covariances: FloatArray, max_radius: float, level: float = 0.95
) -> FloatArray:
    """Covariances scaled down, each as a whole, so that no ``level`` radius exceeds
    ``max_radius``.

    An estimate and its target both lie on the room's floor, so a confidence circle wider
    than the floor's diagonal says no more than the diagonal itself: it holds the truth in
    any case. Fits that the data barely determine (the power model's ``M`` values for ``K``
    targets with ``2 K + 1 > M`` unknowns) have a singular information and so covariances of
    round-off size, and sometimes, computed in that round-off, no covariance at all (a
    negative variance); bounded, they say "anywhere in the room" in numbers a client can
    use. A covariance times ``c`` has its radius times ``sqrt(c)``, so the shape is kept.
    A singular one (smaller eigenvalue below 1e-12 of the larger, zero included) says
    nothing either: the direction it calls exact is the one the fit had no information on,
    which a pseudo-inverse sets to 0.

    Parameters
    ----------
    covariances : ndarray of shape (K, 2, 2), m^2
    max_radius : float, metres, positive
    level : float, default=0.95

    Returns
    -------
    bounded : ndarray of shape (K, 2, 2), m^2 (what is no covariance, non-finite, singular
        or indefinite, becomes the circle of radius ``max_radius``)

    Examples
    --------
    >>> bounded = bounded_covariances(np.eye(2)[np.newaxis] * 1e20, 5.0)
    >>> round(float(confidence_radii(bounded)[0]), 6)
    5.0
    """
    if not (math.isfinite(max_radius) and max_radius > 0.0):
        raise ValueError(f"max_radius must be positive and finite, got {max_radius}")
    bounded = np.array(covariances, dtype=np.float64)
    # The circle of radius r holds 1 - exp(-r^2 / (2 s)) of N(0, s I), and a covariance
    # below s I has a smaller radius: only those with a trace above s can be too wide.
    circle = max_radius**2 / (-2.0 * math.log1p(-level))
    if all(_inside_circle(covariance, circle) for covariance in bounded.tolist()):
        return bounded  # the common case, once per answer: nothing to bound
    with np.errstate(invalid="ignore", over="ignore"):
        first, second = bounded[:, 0, 0], bounded[:, 1, 1]
        cross = 0.5 * (bounded[:, 0, 1] + bounded[:, 1, 0])
        product = first * second
        valid = (
            np.all(np.isfinite(bounded), axis=(1, 2))
            & (first >= 0.0)
            & (second >= 0.0)
            & (product - cross**2 > _MIN_EIGENVALUE_RATIO * (first + second) ** 2)
        )
        trace = np.where(valid, first + second, 0.0)
    if valid.all() and float(trace.max(initial=0.0)) <= circle:
        return bounded  # the common case, once per answer: nothing to bound
    check = valid & (trace > circle)
    if np.any(check):
        radii = confidence_radii(bounded[check], level)
        factors = np.minimum(1.0, max_radius / radii) ** 2
        bounded[check] *= factors[:, np.newaxis, np.newaxis]
    bounded[~valid] = circle * np.eye(2)
    return bounded


def _inside_circle(covariance: list[list[float]], circle: float) -> bool:
    """Whether one covariance (2 x 2, as lists) is one that :func:`bounded_covariances`
    leaves as it is: finite, not singular nor indefinite, with a trace of at most
    ``circle``. In Python floats, the same operations as the vectorised test: an answer's
    few estimates cost less so."""
    (first, xy), (yx, second) = covariance
    cross = 0.5 * (xy + yx)
    trace = first + second
    return (
        math.isfinite(first)
        and math.isfinite(xy)
        and math.isfinite(yx)
        and math.isfinite(second)
        and first >= 0.0
        and second >= 0.0
        and first * second - cross * cross > _MIN_EIGENVALUE_RATIO * (trace * trace)
        and trace <= circle
    )
