"""Simulated measurements: target placements and per-terminal pilot amplitudes.

:mod:`._ideal` draws them from the paper's model (the layout exactly as given);
:func:`simulate_terminals` from a room with :class:`Impairments` (reflections, terminal gains,
heights and tilts, LED tolerances) unknown to the layout; :mod:`.walkers` moves people along
paths and measures every step (:func:`simulate_walk`, with shadowing).
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
from .walkers import (
    SimulatedWalk,
    WalkerPaths,
    crossing_paths,
    random_waypoint_paths,
    simulate_walk,
)

__all__ = [
    "TRUE_ELEMENT_SIZE_M",
    "Impairments",
    "SimulatedTerminals",
    "SimulatedWalk",
    "WalkerPaths",
    "crossing_paths",
    "mean_signal_power",
    "noise_std_for_snr",
    "noisy_amplitudes",
    "random_positions",
    "random_waypoint_paths",
    "simulate_terminals",
    "simulate_walk",
    "true_amplitudes",
]
