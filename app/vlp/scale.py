"""Is a measurement in the fingerprint's units at all?

A measurement whose signal is far larger than any placement of its targets in the room could
give was sent in other units (raw ADC counts, a pilot amplitude of 1 where the room says
otherwise, volts for amperes) or belongs to another room: it is refused rather than answered
with confident positions pinned to the room's brightest corners. A measurement far too weak
is answered (the lights may be dimmed, a terminal may be covered) and flagged by the fit's
scale (see :mod:`app.vlp.uncertainty`).
"""

from __future__ import annotations

import functools

import numpy as np

from .errors import MeasurementError
from .fingerprints import Fingerprint
from .measurements import Measurement
from .typing import FloatArray, IntArray

__all__ = ["MAX_SCALE_FACTOR", "check_amplitude_scale", "check_measurement_scale"]

# A measurement this many times (in its own units) above the brightest possible is refused.
MAX_SCALE_FACTOR = 100.0


def brightest_energy(fingerprint: Fingerprint) -> float:
    """``max_j sum_i (h_ij x_i)^2``: the most received power any grid point gets (power units)."""

    return float(fingerprint.received_power()[0].max())


@functools.lru_cache(maxsize=64)
def _diagonal(n_leds: int) -> IntArray:
    """Where the diagonal of an M x M matrix sits in its upper-triangle vector (read-only)."""
    upper, lower = np.triu_indices(n_leds)
    found = np.flatnonzero(upper == lower)
    found.setflags(write=False)
    return found


def check_measurement_scale(
    fingerprint: Fingerprint, measurement: Measurement, n_targets: int | None
) -> float:
    """Refuse an aggregated measurement 100x or more above the room's scale.

    The total received power (``sum p`` or ``trace R``) per target is compared with the
    brightest grid point's; with K unknown, one target (K up to 64 cannot reach 100x).

    Returns
    -------
    factor : float
        The measurement's power per target over the brightest point's.

    Raises
    ------
    MeasurementError
        When the factor is at least :data:`MAX_SCALE_FACTOR`; ``field`` names the model.
    """
    values = measurement.values
    if measurement.model == "power":
        total = float(np.sum(values))
    else:
        total = float(values[_diagonal(measurement.n_leds)].sum())
    factor = total / max(n_targets or 1, 1) / max(brightest_energy(fingerprint), 1e-300)
    if factor >= MAX_SCALE_FACTOR:
        raise MeasurementError(
            f"the {measurement.model} measurement is {factor:.3g}x larger than any placement "
            f"of {n_targets or 1} target(s) in this room could give: check its units and the "
            "room's pilot amplitudes",
            field=measurement.model,
        )
    return factor


def check_amplitude_scale(fingerprint: Fingerprint, amplitudes: FloatArray) -> float:
    """Refuse terminals' amplitudes whose typical terminal is 100x or more above the room's
    scale (amplitude units: the root of a terminal's received power over the brightest
    point's, median over the terminals).

    Raises
    ------
    MeasurementError
        ``field="terminals"`` when the factor is at least :data:`MAX_SCALE_FACTOR`.
    """
    energy = np.einsum("km,km->k", amplitudes, amplitudes)
    # A lone terminal's median is its own value: NumPy's median of one value costs about
    # 7 us, 1 % of a lone terminal's whole solve.
    typical = energy[0] if energy.size == 1 else np.median(energy)
    factor = float(np.sqrt(typical / max(brightest_energy(fingerprint), 1e-300)))
    if factor >= MAX_SCALE_FACTOR:
        raise MeasurementError(
            f"the terminals' amplitudes are {factor:.3g}x larger than any point of this room "
            "could receive: check their units and the room's pilot amplitudes",
            field="terminals",
        )
    return factor
