"""Compiled 95 % radii: :func:`app.vlp.radii.confidence_radii` in one call.

Its NumPy reference, :func:`app.vlp.radii.covariance_radii_reference`, documents the
method (each covariance's eigenvalues, then the radial probability of a 2-D Gaussian error by
Gauss-Legendre quadrature, Newton's method kept inside a bracket). Every answer asks for one
radius per estimate (the service, for the answer; the solver's bound on the covariances only
for estimates that may exceed it); in NumPy that is some forty array calls, each Newton step
some twenty over (K, nodes). Here the eigenvalues of each symmetric 2 x 2 matrix are LAPACK's
own closed form (``dlae2``, which the reference's ``eigvalsh`` reaches for a 2 x 2 block), and
each estimate iterates alone to the tolerance; an estimate the reference keeps iterating
until the others converge moves by round-off only. ``2 Phi(x) - 1`` is ``erf(x / sqrt 2)``.
Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ._kernels import compiled
from .typing import FloatArray

__all__ = ["covariance_radii_kernel"]

_ROOT_TWO = math.sqrt(2.0)
_ROOT_TWO_PI = math.sqrt(2.0 * math.pi)


# LAPACK's relative machine precision (dlamch('E')): dsterf's test for a negligible
# off-diagonal entry.
_EPS = 2.0**-53


@compiled
def _eigenvalues(a: float, b: float, c: float) -> tuple[float, float]:
    """The eigenvalues ``(l1, l2)``, ``l1 >= l2``, of ``[[a, b], [b, c]]`` as LAPACK's
    ``dsterf`` computes them for ``eigvalsh``: the diagonal itself when ``b`` is negligible,
    else ``dlae2`` (the one larger in magnitude first, the other from the determinant)."""
    if abs(b) <= (math.sqrt(abs(a)) * math.sqrt(abs(c))) * _EPS or b * b <= (
        _EPS * _EPS * abs(a * c)
    ):
        return max(a, c), min(a, c)
    total = a + c
    difference = abs(a - c)
    twice = abs(b + b)
    if abs(a) > abs(c):
        larger, smaller = a, c
    else:
        larger, smaller = c, a
    if difference > twice:
        quotient = twice / difference
        root = difference * math.sqrt(1.0 + quotient * quotient)
    elif difference < twice:
        quotient = difference / twice
        root = twice * math.sqrt(1.0 + quotient * quotient)
    else:
        root = twice * math.sqrt(2.0)
    if total < 0.0:
        first = 0.5 * (total - root)
        second = (larger / first) * smaller - (b / first) * b
    elif total > 0.0:
        first = 0.5 * (total + root)
        second = (larger / first) * smaller - (b / first) * b
    else:
        first = 0.5 * root
        second = -0.5 * root
    return max(first, second), min(first, second)


@compiled
def covariance_radii_kernel(
    covariances: FloatArray,
    level: float,
    one_d: float,
    two_d: float,
    quadrature: tuple[FloatArray, FloatArray, FloatArray],
    tolerance: float,
    max_steps: int,
) -> FloatArray:
    """The ``level`` radius of each covariance (K, 2, 2): inf where not finite, 0 where its
    larger eigenvalue is not positive; ``quadrature`` = (weights, sines, cosines) of the
    nodes."""
    weights, sines, cosines = quadrature
    out = np.zeros(covariances.shape[0])
    for i in range(covariances.shape[0]):
        xx, xy = covariances[i, 0, 0], covariances[i, 0, 1]
        yx, yy = covariances[i, 1, 0], covariances[i, 1, 1]
        if not (
            math.isfinite(xx) and math.isfinite(xy) and math.isfinite(yx) and math.isfinite(yy)
        ):
            out[i] = math.inf
            continue
        major, minor = _eigenvalues(0.5 * (xx + xx), 0.5 * (yx + xy), 0.5 * (yy + yy))
        if not major > 0.0:
            continue
        ratio = math.sqrt(max(minor / major, 1e-300))
        low = 0.0
        high = two_d * 1.01
        reach = one_d + (two_d - one_d) * ratio
        for _ in range(max_steps):
            u = reach
            excess = 0.0
            slope = 0.0
            for j in range(weights.shape[0]):
                along = u * sines[j]
                across = u * cosines[j] / ratio
                density = math.exp(-0.5 * along * along) / _ROOT_TWO_PI
                inner = math.erf(across / _ROOT_TWO)
                excess += weights[j] * density * inner * u * cosines[j]
                slope += (
                    weights[j]
                    * cosines[j]
                    * density
                    * (
                        (1.0 - along * along) * inner
                        + u
                        * (2.0 / _ROOT_TWO_PI)
                        * math.exp(-0.5 * across * across)
                        * cosines[j]
                        / ratio
                    )
                )
            excess -= level
            if abs(excess) <= tolerance:
                break
            if excess < 0.0:
                low = reach
            elif excess > 0.0:
                high = reach
            # Newton's step while it stays inside the bracket, else bisection.
            step = reach - excess / slope if slope > 0.0 else math.nan
            reach = step if low < step < high else 0.5 * (low + high)
        out[i] = math.sqrt(major) * reach
    return out
