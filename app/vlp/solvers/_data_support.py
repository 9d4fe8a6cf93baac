"""Which nuisances a terminal's own data can support.

A terminal of a 5-LED room sends 5 numbers; its position takes 2 of them, its gain one, and
a free photodiode tilt two more: nothing is left to tell the tilt from the noise, and the
tilt trades against the position. So a nuisance is fitted only when

1. the detected LEDs leave degrees of freedom for it: at least :data:`MIN_RESIDUAL_DOF`
   after the parameters fitted already and the nuisance's own (a count rule); and
2. its fit lowers the whitened cost by more than chance would and by more than the
   Bayesian information criterion's price, ``n_extra ln(n_detected)`` (evidence).

What is not fitted is not lost: the callers carry it into the radius as a model error
(the tilt and height columns of the terminal's misfit design). Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ..typing import FloatArray

__all__ = ["DETECTED_SNR", "MIN_RESIDUAL_DOF", "detected_leds", "supports_nuisance"]

# Residual degrees of freedom a fit must keep after a nuisance: with fewer, the noise
# estimate of the pooled fit and the test below have nothing to stand on.
MIN_RESIDUAL_DOF = 2
# An amplitude counts as a detected LED when it stands this many noise sd above zero.
DETECTED_SNR = 3.0


def detected_leds(amplitudes: FloatArray, sigma2: float | FloatArray | None) -> int:
    """How many of a terminal's amplitudes (M,) are detected: above ``DETECTED_SNR`` noise
    sd (``sigma2``, scalar or per LED), or above zero when the noise is not known yet."""
    values = np.asarray(amplitudes, dtype=np.float64)
    if sigma2 is None:
        return int(np.count_nonzero(values > 0.0))
    threshold = DETECTED_SNR * np.sqrt(np.maximum(np.asarray(sigma2, dtype=np.float64), 0.0))
    return int(np.count_nonzero(values > threshold))


def leaves_dof(n_detected: int, n_params: int, n_extra: int) -> bool:
    """The count rule: ``n_detected - n_params - n_extra >= MIN_RESIDUAL_DOF``."""
    return n_detected - n_params - n_extra >= MIN_RESIDUAL_DOF


def supports_nuisance(
    cost_drop: float, n_detected: int, n_params: int, n_extra: int, chance: float
) -> bool:
    """Whether ``n_extra`` nuisance parameters earn their place in a fit of ``n_params``
    to ``n_detected`` LEDs: the count rule (:func:`leaves_dof`), and a cost decrease
    ``cost_drop`` (whitened, chi-square units) above both ``chance`` (the caller's
    significance level) and the BIC price ``n_extra ln(n_detected)``."""
    if not leaves_dof(n_detected, n_params, n_extra):
        return False
    return cost_drop > max(chance, n_extra * math.log(max(n_detected, 1)))
