"""Aggregated measurements: the power vector (CSM-VLP) and the correlation matrix (CoCSM-VLP).

Terminal ``k`` estimates per LED ``i`` the pilot amplitude ``a_ik = h_ik x_i + noise``.
Cooperating terminals aggregate ``p_i = sum_k a_ik^2`` (model ``power``) or
``R_il = sum_k a_ik a_lk`` (model ``correlation``), sent whole or as ``vech(R)``: the
entries ``i <= l`` in ``numpy.triu_indices(M)`` order. The constant noise term is an extra
atom: all ones for power (``sigma^2 1_M``), the diagonal indicator ``vech(I)`` for
correlation.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from .errors import MeasurementError
from .typing import FloatArray, IntArray

__all__ = [
    "MAX_AMPLITUDE",
    "MAX_MAGNITUDE",
    "MIN_MAGNITUDE",
    "MODELS",
    "Measurement",
    "Model",
    "correlation_from_amplitudes",
    "measurement_from_amplitudes",
    "measurement_from_correlation",
    "measurement_from_power",
    "noise_atom",
    "power_from_amplitudes",
    "summed_terminals",
    "unvech",
    "vech",
    "vech_length",
]

Model = Literal["power", "correlation"]
MODELS: tuple[Model, ...] = get_args(Model)
# Relative asymmetry tolerated in a full correlation matrix before it is refused.
_SYMMETRY_RTOL = 1e-6
# Measured values (powers, correlations) are kept within 1e-100..1e100 in magnitude, so
# that the solvers' squares and products stay finite; real pilots are many decades inside.
MAX_MAGNITUDE = 1e100
MIN_MAGNITUDE = 1e-100
# Amplitudes are squared and summed over up to a few thousand terminals.
MAX_AMPLITUDE = 1e48
# R = sum_k a_k a_k^T over K < M terminals has rank K: eigenvalues above _RANK_SIGNAL of the
# largest count, and the rank is read only when all the others are below _RANK_NULL of it
# (round-off of float64 sums is ~1e-15; three decades between the two thresholds).
_RANK_SIGNAL = 1e-9
_RANK_NULL = 1e-12
# The eigenvalues cost O(M^3): beyond this many LEDs more than the solve they would save.
_RANK_MAX_LEDS = 256


@dataclass(frozen=True)
class Measurement:
    """One aggregated measurement, ready for a solver.

    Attributes
    ----------
    model : {"power", "correlation"}
    values : ndarray of shape (M,) for power, (M(M+1)/2,) for correlation
        ``p`` or ``vech(R)``, in squared amplitude units.
    n_leds : int
        M.
    """

    model: Model
    values: FloatArray
    n_leds: int

    def correlation(self) -> FloatArray:
        """The full symmetric M x M matrix (correlation model only)."""
        if self.model != "correlation":
            raise MeasurementError("a power measurement has no correlation matrix", field="model")
        return unvech(self.values, self.n_leds)


def vech_length(n_leds: int) -> int:
    """M(M+1)/2."""
    return n_leds * (n_leds + 1) // 2


def vech(matrix: FloatArray) -> FloatArray:
    """Upper triangle (with diagonal) of a square matrix in ``numpy.triu_indices`` order."""
    matrix = np.asarray(matrix, dtype=np.float64)
    return np.asarray(matrix[_upper_triangle(matrix.shape[0])])


def unvech(values: FloatArray, n_leds: int) -> FloatArray:
    """The symmetric M x M matrix whose :func:`vech` is ``values``."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (vech_length(n_leds),):
        raise MeasurementError(
            f"expected {vech_length(n_leds)} upper-triangle entries for {n_leds} LEDs, "
            f"got shape {values.shape}",
            field="correlation",
        )
    upper = np.zeros((n_leds, n_leds))
    upper[_upper_triangle(n_leds)] = values
    return np.asarray(upper + np.triu(upper, 1).T)


def noise_atom(model: Model, n_leds: int) -> FloatArray:
    """The noise-power atom: ones(M) for power, vech(I_M) for correlation."""
    if model == "power":
        return np.ones(n_leds)
    return vech(np.eye(n_leds))


def _as_finite(values: object, field: str, limit: float = MAX_MAGNITUDE) -> FloatArray:
    return _finite_and_largest(values, field, limit)[0]


def _finite_and_largest(
    values: object, field: str, limit: float = MAX_MAGNITUDE
) -> tuple[FloatArray, float]:
    """The values as a float array and their largest magnitude (0 when there are none).

    Raises
    ------
    MeasurementError
        Naming ``field``: not numbers, NaN or infinite, above ``limit`` or below
        :data:`MIN_MAGNITUDE` in magnitude everywhere (and not all zero).
    """
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeasurementError(f"{field} must contain only numbers", field=field) from exc
    # One reduction for both rules: the largest magnitude is NaN or infinite exactly when
    # some value is (the array's own methods: numpy's module functions wrap them, at a cost
    # several times that of the work on a few hundred numbers).
    largest = float(np.abs(array).max()) if array.size else 0.0
    if not math.isfinite(largest):
        raise MeasurementError(f"{field} contains NaN or infinite values", field=field)
    if largest > limit:
        raise MeasurementError(
            f"{field} values must be at most {limit:.0e} in magnitude, got {largest:.3g}",
            field=field,
        )
    if 0.0 < largest < MIN_MAGNITUDE:
        raise MeasurementError(
            f"{field} is below {MIN_MAGNITUDE:.0e} everywhere (largest {largest:.3g}): "
            "no pilot was received",
            field=field,
        )
    return array, largest


def power_from_amplitudes(amplitudes: FloatArray) -> FloatArray:
    """``p_i = sum_k a_ik^2`` from amplitudes of shape (K, M); returns shape (M,)."""
    amps = np.atleast_2d(_as_finite(amplitudes, "amplitudes", MAX_AMPLITUDE))
    return np.asarray(np.einsum("km,km->m", amps, amps))


def correlation_from_amplitudes(amplitudes: FloatArray) -> FloatArray:
    """``R = sum_k a_k a_k^T`` from amplitudes of shape (K, M); returns shape (M, M)."""
    amps = np.atleast_2d(_as_finite(amplitudes, "amplitudes", MAX_AMPLITUDE))
    return np.asarray(amps.T @ amps)


def measurement_from_power(power: object, n_leds: int) -> Measurement:
    """Validate a power vector of M nonnegative numbers, not all zero."""
    values = _as_finite(power, "power")
    if values.shape != (n_leds,):
        raise MeasurementError(
            f"power must have {n_leds} entries (one per LED), got shape {values.shape}",
            field="power",
        )
    if np.any(values < 0):
        raise MeasurementError(
            "power entries must be >= 0 (they are sums of squares)", field="power"
        )
    if not np.any(values > 0):
        raise MeasurementError("power is all zero: no pilot was received", field="power")
    return Measurement(model="power", values=values, n_leds=n_leds)


def measurement_from_correlation(correlation: object, n_leds: int) -> Measurement:
    """Validate a correlation matrix (M x M, symmetric) or its upper triangle (M(M+1)/2)."""
    values, scale = _finite_and_largest(correlation, "correlation")
    if values.shape == (n_leds, n_leds):
        # The triangle and its mirror, read as flat positions: |R_il - R_li| is the same
        # number either way round, so the largest over the triangle is the matrix's.
        upper, lower = _flat_triangles(n_leds)
        flat = values.ravel()
        above, below = flat[upper], flat[lower]
        if np.abs(above - below).max() > _SYMMETRY_RTOL * max(scale, 1e-300):
            raise MeasurementError("correlation matrix must be symmetric", field="correlation")
        values = 0.5 * (above + below)
    elif values.shape != (vech_length(n_leds),):
        raise MeasurementError(
            f"correlation must be a {n_leds} x {n_leds} matrix or its {vech_length(n_leds)} "
            f"upper-triangle entries, got shape {values.shape}",
            field="correlation",
        )
    diagonal = values[_diagonal_positions(n_leds)]
    if diagonal.size and diagonal.min() < 0:
        raise MeasurementError("correlation diagonal entries must be >= 0", field="correlation")
    if not (diagonal.size and diagonal.max() > 0):
        raise MeasurementError(
            "correlation is all zero on its diagonal: no pilot was received", field="correlation"
        )
    return Measurement(model="correlation", values=values, n_leds=n_leds)


def summed_terminals(measurement: Measurement) -> int | None:
    """How many terminals a correlation measurement sums, read off its rank.

    ``R = sum_k a_k a_k^T`` over K terminals (the contract's aggregation) has rank K
    whenever K < M, whatever the noise (it is in the amplitudes ``a_k``, not added to
    ``R``), the terminals' gains or a common scale. So its spectrum counts the terminals
    exactly where a rule on the signal's energy depends on the fingerprint's scale. Two
    terminals a few centimetres apart still count as two.

    Parameters
    ----------
    measurement : Measurement

    Returns
    -------
    int or None
        K; None where the spectrum does not say: the power model, K >= M, a matrix that
        is not such a sum (averaged over noisy samples, rounded in transit, not positive
        semi-definite), or more than a few hundred LEDs.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> amplitudes = rng.uniform(0.1, 1.0, size=(3, 16))  # 3 terminals, 16 LEDs
    >>> summed_terminals(measurement_from_amplitudes(amplitudes, "correlation", 16))
    3
    >>> summed_terminals(measurement_from_amplitudes(amplitudes, "power", 16)) is None
    True
    """
    n_leds = measurement.n_leds
    if measurement.model != "correlation" or n_leds > _RANK_MAX_LEDS:
        return None
    eigenvalues = np.linalg.eigvalsh(unvech(measurement.values, n_leds))
    largest = float(np.max(np.abs(eigenvalues)))
    if not largest > 0.0:
        return None
    relative = eigenvalues / largest
    signal = int(np.sum(relative > _RANK_SIGNAL))
    # Anything between the thresholds, or a negative eigenvalue beyond round-off: no sum of
    # K outer products.
    if signal >= n_leds or np.any(np.abs(relative[relative <= _RANK_SIGNAL]) > _RANK_NULL):
        return None
    return signal


def measurement_from_amplitudes(amplitudes: object, model: Model, n_leds: int) -> Measurement:
    """Aggregate per-terminal amplitudes of shape (K, M) into a measurement of ``model``."""
    amps = np.atleast_2d(_as_finite(amplitudes, "amplitudes"))
    if amps.ndim != 2 or amps.shape[1] != n_leds:
        raise MeasurementError(
            f"amplitudes must have {n_leds} entries per terminal, got shape {amps.shape}",
            field="terminals",
        )
    if model == "power":
        return measurement_from_power(power_from_amplitudes(amps), n_leds)
    return measurement_from_correlation(vech(correlation_from_amplitudes(amps)), n_leds)


@functools.lru_cache(maxsize=8)
def _upper_triangle(n_leds: int) -> tuple[IntArray, IntArray]:
    """``numpy.triu_indices(n_leds)``, made once per M (1024 LEDs: 8 MB, ~10 ms to make)."""
    upper, lower = np.triu_indices(n_leds)
    upper.flags.writeable = False
    lower.flags.writeable = False
    return upper, lower


@functools.lru_cache(maxsize=8)
def _flat_triangles(n_leds: int) -> tuple[IntArray, IntArray]:
    """The flat positions in an M x M matrix of :func:`vech`'s entries (i, l) and of their
    mirrors (l, i), made once per M."""
    upper, lower = _upper_triangle(n_leds)
    above = upper * n_leds + lower
    below = lower * n_leds + upper
    above.flags.writeable = False
    below.flags.writeable = False
    return above, below


@functools.lru_cache(maxsize=8)
def _diagonal_positions(n_leds: int) -> IntArray:
    """Position of (i, i) in vech order: row i starts after sum_{r<i} (M - r) entries."""
    rows = np.arange(n_leds)
    positions = np.asarray(rows * n_leds - rows * (rows - 1) // 2)
    positions.flags.writeable = False
    return positions
