"""Simulated measurements: target placements and noisy per-terminal pilot amplitudes.

SNR convention (the one ``POST /v1/rooms/{room_id}/simulate`` documents, see
:mod:`app.schemas.simulate`): the mean over LEDs and grid points of
``(h_ij x_i)^2`` divided by the noise variance of one amplitude. So at ``snr_db`` every
amplitude ``a_ik = h_ik x_i + n_ik`` gets i.i.d. ``n_ik ~ N(0, sigma^2)`` with
``sigma^2 = mean(J) / 10^(snr_db / 10)``.
"""

from __future__ import annotations

import numpy as np

from ..channel import channel_gains
from ..errors import SolverError
from ..fingerprints import Fingerprint
from ..layout import Layout
from ..rng import RandomState, as_generator
from ..typing import FloatArray

__all__ = [
    "mean_signal_power",
    "noise_std_for_snr",
    "noisy_amplitudes",
    "random_positions",
    "true_amplitudes",
]


def mean_signal_power(fingerprint: Fingerprint) -> float:
    """Mean of ``(h_ij x_i)^2`` over all LEDs and grid points (zeros outside the FOV count)."""
    return fingerprint.received_power()[1] / (fingerprint.n_leds * fingerprint.n_cells)


def noise_std_for_snr(fingerprint: Fingerprint, snr_db: float) -> float:
    """Standard deviation sigma of one amplitude's noise at ``snr_db`` (our SNR convention)."""
    return float(np.sqrt(mean_signal_power(fingerprint) / 10.0 ** (snr_db / 10.0)))


def random_positions(
    layout: Layout,
    n_targets: int,
    *,
    on_grid: bool = False,
    distinct_cells: bool = True,
    rng: RandomState = None,
) -> FloatArray:
    """K target positions, uniformly random in the room (or at random distinct grid centres).

    Parameters
    ----------
    layout : Layout
    n_targets : int
        K >= 1 (at most N when ``on_grid`` or ``distinct_cells``).
    on_grid : bool, default=False
        Place targets at grid centres instead of anywhere.
    distinct_cells : bool, default=True
        No two targets in one grid cell (as the paper's occupancy vector assumes).
    rng : Generator, int or None

    Returns
    -------
    positions : ndarray of shape (K, 2), metres
    """
    gen = as_generator(rng)
    if n_targets < 1 or ((on_grid or distinct_cells) and n_targets > layout.n_cells):
        raise SolverError(
            f"cannot place {n_targets} targets on {layout.n_cells} grid points", field="targets"
        )
    if on_grid or distinct_cells:
        cells = gen.choice(layout.n_cells, size=n_targets, replace=False)
        centres = layout.cell_centres(cells)
        if on_grid:
            return centres
        jitter = gen.uniform(-0.5, 0.5, size=(n_targets, 2)) * layout.grid.step
        return np.asarray(centres + jitter)
    extent = np.array([layout.room.length, layout.room.width])
    return np.asarray(gen.uniform(0.0, 1.0, size=(n_targets, 2)) * extent)


def true_amplitudes(layout: Layout, positions: FloatArray) -> FloatArray:
    """Noiseless amplitudes ``h_ik x_i``, ndarray of shape (K, M)."""
    gains = channel_gains(layout, positions)  # (M, K)
    return np.asarray((gains * layout.pilot_amplitudes[:, None]).T)


def noisy_amplitudes(
    layout: Layout, positions: FloatArray, noise_std: float, *, rng: RandomState = None
) -> FloatArray:
    """Amplitudes with i.i.d. Gaussian noise of standard deviation ``noise_std``, shape (K, M)."""
    clean = true_amplitudes(layout, positions)
    gen = as_generator(rng)
    return np.asarray(clean + noise_std * gen.standard_normal(clean.shape))
