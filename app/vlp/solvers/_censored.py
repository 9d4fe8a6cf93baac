"""LEDs a terminal did not detect: censored amplitudes, below its detection floor.

A terminal that did not detect LED i knows only ``0 <= a_i < f`` (``f`` its detection
floor). Sent as a zero or as the floor, the fit would believe a number the receiver never
measured. The per-terminal fit is a weighted least-squares fit, so the censored reading
enters it as the first two moments of that interval: the value ``f / 2`` with the variance
``f^2 / 12`` of a uniform amplitude below the floor (added to the noise's). A model that
predicts a strong amplitude there is penalised, one that predicts anything below the floor
about equally little, and the LED counts as not detected for the nuisances' data support
(its value stands less than 3 sd above zero: :mod:`._data_support`).

Without a floor of its own, a terminal's floor is the weakest amplitude it detected (the
contract's default). Private: callers validate.
"""

from __future__ import annotations

import numpy as np

from ..typing import FloatArray

__all__ = ["censored_substitutes", "detection_floors", "with_censored_variance"]


def detection_floors(amplitudes: FloatArray, floors: FloatArray | None) -> FloatArray:
    """Each terminal's detection floor (K,): its own (``floors[k]``, NaN = not sent), else
    the weakest amplitude it detected; ``amplitudes`` (K, M) hold NaN where not detected."""
    detected = np.where(np.isfinite(amplitudes), amplitudes, np.inf)
    weakest = np.min(detected, axis=1) if amplitudes.shape[1] else np.zeros(len(amplitudes))
    weakest = np.where(np.isfinite(weakest), weakest, 0.0)
    if floors is None:
        return np.asarray(weakest, dtype=np.float64)
    own = np.asarray(floors, dtype=np.float64)
    return np.where(np.isfinite(own), own, weakest)


def censored_substitutes(
    amplitudes: FloatArray, floors: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Amplitudes (K, M) with each NaN (not detected) replaced by half its terminal's floor,
    and the extra variance (K, M) of each entry: ``floor^2 / 12`` where censored, else 0."""
    values = np.asarray(amplitudes, dtype=np.float64)
    censored = ~np.isfinite(values)
    if not censored.any():
        return values, np.zeros_like(values)
    floor = detection_floors(values, floors)[:, None]
    filled = np.where(censored, 0.5 * floor, values)
    extra = np.where(censored, floor**2 / 12.0, 0.0)
    return filled, extra


def with_censored_variance(sigma2: float | FloatArray, extra: FloatArray) -> float | FloatArray:
    """A terminal's amplitude variances: ``sigma2`` (scalar or per LED) plus ``extra`` (M,),
    the censored entries' own; ``sigma2`` unchanged when nothing is censored."""
    if not np.any(extra):
        return sigma2
    return np.asarray(sigma2, dtype=np.float64) + extra
