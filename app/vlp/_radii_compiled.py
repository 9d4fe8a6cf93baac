"""Compiled 95 % radii: the Newton iteration of :func:`app.vlp.uncertainty.confidence_radii`.

Its NumPy reference, :func:`app.vlp.uncertainty.radial_roots_reference`, documents the
method (the radial probability of a 2-D Gaussian error by Gauss-Legendre quadrature, Newton's
method kept inside a bracket). Every answer asks for one radius per estimate (the service,
for the answer; the solver's bound on the covariances only for estimates that may exceed it);
in NumPy each Newton step is some twenty array calls over (K, nodes).
Here each estimate iterates alone to the tolerance; an estimate the reference keeps
iterating until the others converge moves by round-off only. ``2 Phi(x) - 1`` is
``erf(x / sqrt 2)``. Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ._kernels import compiled
from .typing import FloatArray

__all__ = ["radial_roots_kernel"]

_ROOT_TWO = math.sqrt(2.0)
_ROOT_TWO_PI = math.sqrt(2.0 * math.pi)


@compiled
def radial_roots_kernel(
    root_ratio: FloatArray,
    level: float,
    one_d: float,
    two_d: float,
    quadrature: tuple[FloatArray, FloatArray, FloatArray],
    tolerance: float,
    max_steps: int,
) -> FloatArray:
    """``u`` per estimate with ``P(|e| <= u sqrt(l1)) = level``, for ``sqrt(l2 / l1)`` =
    ``root_ratio`` (n,); ``quadrature`` = (weights, sines, cosines) of the nodes."""
    weights, sines, cosines = quadrature
    out = np.empty(root_ratio.shape[0])
    for i in range(root_ratio.shape[0]):
        ratio = root_ratio[i]
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
        out[i] = reach
    return out
