"""Simulated measurements: target placements and per-terminal pilot amplitudes.

:mod:`._ideal` draws them from the paper's model (the layout exactly as given);
:func:`simulate_terminals` from a room with :class:`Impairments` (reflections, terminal gains,
heights and tilts, LED tolerances) unknown to the layout.
"""

from __future__ import annotations

from ._ideal import (
    mean_signal_power,
    noise_std_for_snr,
    noisy_amplitudes,
    random_positions,
    true_amplitudes,
)
from .impairments import Impairments
from .terminals import TRUE_ELEMENT_SIZE_M, SimulatedTerminals, simulate_terminals

__all__ = [
    "TRUE_ELEMENT_SIZE_M",
    "Impairments",
    "SimulatedTerminals",
    "mean_signal_power",
    "noise_std_for_snr",
    "noisy_amplitudes",
    "random_positions",
    "simulate_terminals",
    "true_amplitudes",
]
