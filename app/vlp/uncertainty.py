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
from scipy import optimize, special

from .typing import FloatArray

__all__ = [
    "POOR_FIT_CHI2",
    "SCALE_MISMATCH_FACTOR",
    "FitQuality",
    "Quality",
    "assess_fit",
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

    For a zero-mean 2-D Gaussian error with covariance eigenvalues ``l1 >= l2``,
    ``|e|^2 = l1 X^2 + l2 Y^2`` with X, Y independent standard normals, so with
    ``X = a sin(t)``, ``a = r / sqrt(l1)``:
    ``P(|e| <= r) = int_{-pi/2}^{pi/2} phi(a sin t) (2 Phi(r cos(t) / sqrt(l2)) - 1) a cos(t) dt``
    (Gauss-Legendre), solved for ``r`` by bisection.

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
    cov = np.asarray(covariance, dtype=np.float64)
    eigen = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    if not np.all(np.isfinite(eigen)):
        return math.inf
    major = float(eigen[-1])
    if major <= 0.0:
        return 0.0
    minor = max(float(eigen[0]), major * 1e-300, 1e-300)
    cosines = np.cos(_ANGLES)
    sines = np.sin(_ANGLES)

    def probability(radius: float) -> float:
        reach = radius / math.sqrt(major)
        inner = 2.0 * special.ndtr(radius * cosines / math.sqrt(minor)) - 1.0
        density = np.exp(-0.5 * (reach * sines) ** 2) / math.sqrt(2.0 * math.pi)
        return float(np.sum(_WEIGHTS * density * inner * reach * cosines))

    # P(0) = 0 < level; at ``high`` (the isotropic radius for the larger variance, 1 % out)
    # P > level since minor <= major: a bracket for Brent's method (~10 evaluations where
    # bisection to the same precision takes 60; this runs for every estimate of an answer).
    high = math.sqrt(major) * math.sqrt(-2.0 * math.log(1.0 - level)) * 1.01
    radius = optimize.brentq(
        lambda r: probability(r) - level, 0.0, high, xtol=1e-15 * high, maxiter=200
    )
    return float(radius)
