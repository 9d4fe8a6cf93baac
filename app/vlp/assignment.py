"""Which terminal is which estimate: matching estimates with per-terminal amplitudes.

The aggregated measurement forgets who is where. When terminals also sent their own
amplitudes, each estimate's predicted amplitudes ``h_i(p) x_i`` can be compared with each
terminal's, and the assignment of least total squared error labels the estimates.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from .channel import channel_gains
from .errors import MeasurementError
from .layout import Layout
from .typing import FloatArray, IntArray

__all__ = ["assign_terminals", "assignment_costs"]


def assignment_costs(layout: Layout, positions: FloatArray, amplitudes: FloatArray) -> FloatArray:
    """Squared amplitude mismatch of every estimate with every terminal.

    Parameters
    ----------
    layout : Layout
    positions : ndarray of shape (K, 2)
        Estimated ``(x, y)``, metres.
    amplitudes : ndarray of shape (K_t, M)
        Each terminal's measured pilot amplitudes.

    Returns
    -------
    costs : ndarray of shape (K, K_t)
        ``||h(p_k) * x - a_t||^2``, squared amplitude units.

    Raises
    ------
    MeasurementError
        On wrong shapes or non-finite values.
    """
    points = np.asarray(positions, dtype=np.float64)
    amps = np.asarray(amplitudes, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise MeasurementError(
            f"positions must have shape (K, 2), got {points.shape}", field="positions"
        )
    if amps.ndim != 2 or amps.shape[1] != layout.n_leds:
        raise MeasurementError(
            f"amplitudes must have shape (K_t, {layout.n_leds}), got {amps.shape}",
            field="terminals",
        )
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(amps))):
        raise MeasurementError("positions and amplitudes must be finite", field="terminals")
    predicted = (channel_gains(layout, points) * layout.pilot_amplitudes[:, None]).T  # (K, M)
    difference = predicted[:, None, :] - amps[None, :, :]
    return np.asarray(np.einsum("ktm,ktm->kt", difference, difference))


def assign_terminals(layout: Layout, positions: FloatArray, amplitudes: FloatArray) -> IntArray:
    """Label each estimate with the terminal whose amplitudes it explains best.

    Parameters
    ----------
    layout : Layout
    positions : ndarray of shape (K, 2)
        Estimated ``(x, y)``, metres.
    amplitudes : ndarray of shape (K_t, M)
        Each terminal's measured pilot amplitudes (the rows of the ``terminals`` input).

    Returns
    -------
    terminals : ndarray of shape (K,)
        Row of ``amplitudes`` assigned to each estimate, or -1 for estimates left over
        when ``K > K_t``. The assignment minimises the total squared mismatch
        (:func:`assignment_costs`, Hungarian algorithm).

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> layout = paper_layout()
    >>> spots = np.array([[0.5, 0.5], [3.0, 2.5]])
    >>> amps = (channel_gains(layout, spots) * layout.pilot_amplitudes[:, None]).T
    >>> assign_terminals(layout, spots[::-1], amps).tolist()
    [1, 0]
    >>> assign_terminals(layout, np.vstack((spots, [[2.0, 2.0]])), amps[:1]).tolist()
    [0, -1, -1]
    """
    costs = assignment_costs(layout, positions, amplitudes)
    labels = np.full(costs.shape[0], -1, dtype=np.intp)
    if costs.size:
        rows, cols = linear_sum_assignment(costs)
        labels[rows] = cols
    return labels
