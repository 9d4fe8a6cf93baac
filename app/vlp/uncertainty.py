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

from ._typing import FloatArray

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
# Angular quadrature nodes for the 2-D Gaussian's radial probability (periodic trapezoid:
# exponentially accurate).
_ANGLES = np.linspace(0.0, 2.0 * math.pi, 256, endpoint=False)
_DIRECTIONS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)])


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
    """

    chi2_per_dof: float
    scale: float
    quality: Quality
    detail: str


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
    reduced = float(chi2) / max(int(dof), 1)
    if not (1.0 / SCALE_MISMATCH_FACTOR <= scale <= SCALE_MISMATCH_FACTOR):
        detail = (
            f"the measurement is {scale:.3g}x the fingerprint's amplitude scale: check the "
            "units, the pilot amplitudes and the receivers' gain (or calibrate the room)"
        )
        return FitQuality(reduced, scale, "scale_mismatch", detail)
    if reduced > POOR_FIT_CHI2:
        detail = (
            f"the model leaves {reduced:.3g}x the expected residual: the room differs from its "
            "layout (reflections, receivers' gain, height or tilt, LEDs); calibrate the room"
        )
        return FitQuality(reduced, scale, "poor", detail)
    return FitQuality(reduced, scale, "ok", "the model explains the measurement to its noise")


def confidence_radius(covariance: FloatArray, level: float = 0.95) -> float:
    """Radius of the circle around the estimate that holds the truth with ``level``.

    For a zero-mean 2-D Gaussian error with covariance ``C``, in polar coordinates
    ``P(|e| <= r) = 1 / (2 pi sqrt(det C)) * int_0^{2 pi} (1 - exp(-r^2 q / 2)) / q dtheta``
    with ``q = d^T C^-1 d``, ``d = (cos theta, sin theta)``; solved for ``r`` by bisection.

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
    cov = 0.5 * (np.asarray(covariance, dtype=np.float64) + np.asarray(covariance).T)
    eigen = np.linalg.eigvalsh(cov)
    if not np.all(np.isfinite(eigen)) or eigen[-1] <= 0.0:
        return 0.0 if np.all(np.isfinite(eigen)) else math.inf
    floor = max(eigen[-1] * 1e-12, 1e-300)
    cov = cov + np.eye(2) * max(0.0, floor - eigen[0])
    precision = np.linalg.inv(cov)
    quad = np.einsum("ia,ij,ja->a", _DIRECTIONS, precision, _DIRECTIONS)
    norm = 1.0 / (2.0 * math.pi * math.sqrt(max(np.linalg.det(cov), 1e-300)))
    step = 2.0 * math.pi / _ANGLES.shape[0]

    def probability(radius: float) -> float:
        return float(norm * step * np.sum(-np.expm1(-0.5 * radius**2 * quad) / quad))

    low, high = 0.0, math.sqrt(eigen[-1]) * math.sqrt(-2.0 * math.log(1.0 - level)) * 1.01
    for _ in range(60):
        middle = 0.5 * (low + high)
        if probability(middle) < level:
            low = middle
        else:
            high = middle
    return 0.5 * (low + high)
