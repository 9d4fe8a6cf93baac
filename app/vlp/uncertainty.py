"""How much to trust an answer: confidence radii and the goodness of a fit.

A fit's covariance comes from its Fisher information (the Gauss-Newton normal matrix of
the whitened residuals and priors at the optimum), inflated by the misfit when the model
explains the data worse than the noise would (a reduced chi-square above 1: the room differs
from its model, so the noise alone understates the error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import special

from .typing import FloatArray

__all__ = [
    "POOR_FIT_CHI2",
    "SCALE_MISMATCH_FACTOR",
    "FitQuality",
    "Quality",
    "assess_fit",
    "confidence_radii",
    "confidence_radius",
]

Quality = Literal["ok", "poor", "scale_mismatch"]

# A reduced chi-square above this says the model does not explain the measurement (the
# room's reflections, gains or geometry differ from its layout): answered, but flagged.
POOR_FIT_CHI2 = 4.0
# A common amplitude scale outside [1/f, f] says the measurement is not in the fingerprint's
# units (or the pilots / receiver gains changed): answered, but flagged.
SCALE_MISMATCH_FACTOR = 1.5
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
_MAX_RADIUS_STEPS = 60


@dataclass(frozen=True)
class FitQuality:
    """Goodness of one fit.

    Attributes
    ----------
    chi2_per_dof : float
        Whitened residual sum of squares over its degrees of freedom (about 1 when the
        model explains the data down to the noise).
    scale : float
        Fitted common amplitude scale of the measurement relative to the fingerprint
        (1 = exactly as modelled).
    quality : {"ok", "poor", "scale_mismatch"}
    detail : str
        One sentence for a person.
    dof : int
        Degrees of freedom behind ``chi2_per_dof``.
    """

    chi2_per_dof: float
    scale: float
    quality: Quality
    detail: str
    dof: int = 1


def assess_fit(chi2: float, dof: int, scale: float) -> FitQuality:
    """Classify a fit by its reduced chi-square and its common amplitude scale.

    Parameters
    ----------
    chi2 : float
        Whitened residual sum of squares.
    dof : int
        Its degrees of freedom (observations minus fitted parameters); at least 1 is used.
    scale : float
        Fitted common amplitude scale, positive.

    Examples
    --------
    >>> assess_fit(95.0, 100, 1.02).quality
    'ok'
    >>> assess_fit(95.0, 100, 3.0).quality
    'scale_mismatch'
    """
    dof = max(int(dof), 1)
    reduced = float(chi2) / dof
    if not (1.0 / SCALE_MISMATCH_FACTOR <= scale <= SCALE_MISMATCH_FACTOR):
        detail = (
            f"the measurement is {scale:.3g}x the fingerprint's amplitude scale: check the "
            "units, the pilot amplitudes and the receivers' gain (or calibrate the room)"
        )
        return FitQuality(reduced, scale, "scale_mismatch", detail, dof)
    if reduced > POOR_FIT_CHI2:
        detail = (
            f"the model leaves {reduced:.3g}x the expected residual: the room differs from its "
            "layout (reflections, receivers' gain, height or tilt, LEDs); calibrate the room"
        )
        return FitQuality(reduced, scale, "poor", detail, dof)
    return FitQuality(reduced, scale, "ok", "the model explains the measurement to its noise", dof)


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
    radii = np.zeros(cov.shape[0])
    if cov.shape[0] == 0:
        return radii
    finite = np.all(np.isfinite(cov), axis=(1, 2))
    radii[~finite] = math.inf
    eigen = np.zeros((cov.shape[0], 2))
    eigen[finite] = np.linalg.eigvalsh(0.5 * (cov[finite] + cov[finite].transpose(0, 2, 1)))
    major = eigen[:, 1]
    solve = finite & (major > 0.0)
    if not np.any(solve):
        return radii
    major = major[solve]
    ratio = np.maximum(eigen[solve, 0] / major, 1e-300)[:, np.newaxis]
    root_ratio = np.sqrt(ratio)
    two_d = math.sqrt(-2.0 * math.log1p(-level))  # u when rho = 1 (Rayleigh)
    one_d = float(special.ndtri(0.5 + 0.5 * level))  # u when rho -> 0
    # P(0) = 0 < level and P(two_d) >= level (rho <= 1): a bracket for every estimate.
    low = np.zeros(major.size)
    high = np.full(major.size, two_d * 1.01)
    reach = one_d + (two_d - one_d) * root_ratio[:, 0]  # within a few % of the root
    for _ in range(_MAX_RADIUS_STEPS):
        u = reach[:, np.newaxis]
        along = u * _SINES
        across = u * _COSINES / root_ratio
        density = np.exp(-0.5 * along**2) / _ROOT_TWO_PI
        inner = 2.0 * special.ndtr(across) - 1.0
        excess = np.sum(_WEIGHTS * density * inner * u * _COSINES, axis=1) - level
        slope = np.sum(
            _WEIGHTS
            * _COSINES
            * density
            * (
                (1.0 - along**2) * inner
                + u * (2.0 / _ROOT_TWO_PI) * np.exp(-0.5 * across**2) * _COSINES / root_ratio
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
