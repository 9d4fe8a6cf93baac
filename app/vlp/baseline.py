"""The conventional RSS baseline the paper compares with: one terminal at a time.

Each terminal inverts the Lambertian model per LED to a distance, trilaterates from its
strongest LEDs by linear least squares, and refines the position by nonlinear least
squares on all its amplitudes.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .channel import channel_gain_gradients, led_constants
from .errors import MeasurementError
from .layout import Layout
from .typing import FloatArray

__all__ = ["MAX_TRILATERATION_LEDS", "rss_localize"]

# Trilaterate from at most this many of the strongest LEDs (at least 3 are needed).
MAX_TRILATERATION_LEDS = 6


def rss_localize(layout: Layout, amplitudes: FloatArray) -> FloatArray:
    """Locate each terminal from its own received pilot amplitudes.

    Parameters
    ----------
    layout : Layout
    amplitudes : ndarray of shape (K, M)
        Terminal ``k``'s estimate of LED ``i``'s pilot amplitude, ``a_ik = h_ik x_i + noise``.

    Returns
    -------
    positions : ndarray of shape (K, 2)
        Estimated ``(x, y)``, metres, inside the room.

    Raises
    ------
    MeasurementError
        When the amplitudes are not (K, M) or not finite.

    Notes
    -----
    With ``cos(alpha) = cos(phi) = dz/d`` the gain is ``h = C dz^(m+1) / d^(m+3)`` with
    ``C = (m+1) A G_f G_c / (2 pi)``, so ``d_i = (C_i dz_i^(m_i+1) x_i / a_i)^(1/(m_i+3))``
    and the horizontal range is ``r_i^2 = d_i^2 - dz_i^2``. With the unknowns
    ``(x, y, x^2 + y^2)`` the circles ``|p - s_i|^2 = r_i^2`` become linear; the strongest
    LEDs (3 to :data:`MAX_TRILATERATION_LEDS`) give the initial position, which a bounded
    Gauss-Newton (trust-region) fit of ``h_i(p) x_i`` to all the amplitudes then refines.
    With fewer than 3 positive amplitudes the start is the strongest LED's foot point.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> from app.vlp.simulation import true_amplitudes
    >>> layout = paper_layout()
    >>> truth = np.array([[1.23, 2.71], [3.3, 0.4]])
    >>> np.round(rss_localize(layout, true_amplitudes(layout, truth)), 6).tolist()
    [[1.23, 2.71], [3.3, 0.4]]
    """
    amps = np.asarray(amplitudes, dtype=np.float64)
    if amps.ndim == 1:
        amps = amps[None, :]
    if amps.ndim != 2 or amps.shape[1] != layout.n_leds:
        raise MeasurementError(
            f"amplitudes must have shape (K, {layout.n_leds}), got {amps.shape}", field="amplitudes"
        )
    if not np.all(np.isfinite(amps)):
        raise MeasurementError("amplitudes contain NaN or infinite values", field="amplitudes")
    return np.array(
        [_refine(layout, row, _trilaterate(layout, row)) for row in amps], dtype=np.float64
    ).reshape(-1, 2)


def _trilaterate(layout: Layout, amplitudes: FloatArray) -> FloatArray:
    """Linear least-squares position from the strongest LEDs' inverted ranges."""
    leds = layout.led_positions
    orders, prefactors = led_constants(layout)
    gains = amplitudes / layout.pilot_amplitudes
    strongest = np.argsort(-gains, kind="stable")
    usable = strongest[gains[strongest] > 0][:MAX_TRILATERATION_LEDS]
    if usable.size < 3:
        foot = leds[strongest[0], :2]
        return _clip(layout, foot)
    dz = leds[usable, 2] - layout.grid.receiver_height
    m = orders[usable]
    dist = (prefactors[usable] * dz ** (m + 1.0) / gains[usable]) ** (1.0 / (m + 3.0))
    ranges_sq = np.clip(dist**2 - dz**2, 0.0, None)
    centres = leds[usable, :2]
    system = np.column_stack((-2.0 * centres, np.ones(usable.size)))
    rhs = ranges_sq - np.einsum("ij,ij->i", centres, centres)
    solution = np.linalg.lstsq(system, rhs, rcond=None)[0]
    return _clip(layout, solution[:2])


def _refine(layout: Layout, amplitudes: FloatArray, start: FloatArray) -> FloatArray:
    """Bounded nonlinear least squares of the predicted amplitudes on all LEDs."""
    pilots = layout.pilot_amplitudes
    scale = float(np.max(np.abs(amplitudes))) or 1.0

    def residual(point: FloatArray) -> FloatArray:
        gains, _ = channel_gain_gradients(layout, point[None, :])
        return np.asarray((gains[:, 0] * pilots - amplitudes) / scale)

    def jacobian(point: FloatArray) -> FloatArray:
        _, grads = channel_gain_gradients(layout, point[None, :])
        return np.asarray(grads[:, 0, :] * pilots[:, None] / scale)

    upper = np.array([layout.room.length, layout.room.width])
    fit = least_squares(
        residual,
        _interior(layout, start),
        jac=jacobian,
        bounds=(np.zeros(2), upper),
        method="trf",
        x_scale=layout.grid.step,
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=100,
    )
    return _clip(layout, np.asarray(fit.x, dtype=np.float64))


def _clip(layout: Layout, point: FloatArray) -> FloatArray:
    upper = np.array([layout.room.length, layout.room.width])
    return np.asarray(np.clip(point, 0.0, upper), dtype=np.float64)


def _interior(layout: Layout, point: FloatArray) -> FloatArray:
    """``point`` moved strictly inside the room (a start the bounded fit accepts)."""
    upper = np.array([layout.room.length, layout.room.width])
    margin = 1e-9 * upper
    return np.asarray(np.clip(point, margin, upper - margin), dtype=np.float64)
