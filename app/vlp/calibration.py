"""Survey calibration: fit each LED's pilot amplitude and Lambertian order to measured amplitudes.

The paper assumes the channel information is "collected via beforehand channel estimation
indoors". An admin walks a receiver over surveyed points ``p_k`` (on the receivers' plane) and
records, per LED ``i``, the received pilot amplitude ``a_k``. The model (``channel.py``) is

.. math::

    a_k = g\\, x_i\\, h(p_k; m_i) + n_k, \\qquad
    h(p; m) = \\frac{(m+1) A G_f G_c}{2 \\pi} \\frac{dz^{m+1}}{d^{m+3}} \\ (\\phi \\le FOV),

with ``x_i`` the pilot amplitude, ``m_i`` the Lambertian order and ``g`` the receiver's gain
relative to the nominal receiver of the layout.

Identifiability and the choice made here: only the products ``s_i = g x_i`` can be told apart
from amplitudes, so the fit is done on ``(s_i, m_i)``. It then separates into M independent
two-parameter problems (each LED's rows depend only on its own parameters), solved by
``scipy.optimize.least_squares`` with bounds, started from a log-linear fit and from the nominal
values (the lower cost wins). The products are split into one receiver gain ``g`` and per-LED
``x_i`` by fixing the geometric mean of ``x_i / x_i^nominal`` over the healthy LEDs to 1:
``g`` is that geometric mean of ``s_i / x_i^nominal``, so a survey receiver that is uniformly
more or less sensitive than the nominal one is not mistaken for dimmed LEDs. LEDs whose
relative amplitude ``x_i / x_i^nominal`` is below ``dead_below`` are reported dead, below
``dimmed_below`` dimmed. :func:`calibrated_layout` folds ``g`` into the receiver's
``filter_gain``, so the calibrated model reproduces the surveyed amplitudes ``s_i h``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ._calibration_fit import classify, fit_led, led_rows, model_amplitudes, rms_per_led
from ._typing import BoolArray, FloatArray, IntArray
from .channel import led_constants
from .errors import MeasurementError
from .layout import Layout, Led
from .survey import Survey, check_survey, simulate_survey, survey_from_rows

__all__ = [
    "CalibrationResult",
    "Survey",
    "calibrate",
    "calibrated_layout",
    "check_survey",
    "half_power_angle_deg",
    "masked_layout",
    "simulate_survey",
    "survey_from_rows",
]

# An LED is detected when its fitted signal energy over its rows exceeds this many noise
# variances (a fit of two parameters to pure noise gives about chi-squared with 2 d.o.f.).
_DETECTION_SNR = 25.0


@dataclass(frozen=True)
class CalibrationResult:
    """The fitted LED parameters and the quality of the fit, all arrays of shape (M,).

    Attributes
    ----------
    pilot_amplitudes : ndarray of shape (M,)
        Fitted ``x_i`` (layout unit), with the common scale moved into ``receiver_gain``.
        Dead and unsurveyed LEDs keep their nominal value.
    lambertian_orders : ndarray of shape (M,)
        Fitted ``m_i`` (nominal for dead LEDs and LEDs with too few rows in view).
    half_power_angles_deg : ndarray of shape (M,), degrees
        ``arccos(2^(-1/m_i))``.
    receiver_gain : float
        ``g``: the survey receiver's gain relative to the layout's nominal receiver.
    relative_amplitudes : ndarray of shape (M,)
        ``x_i / x_i^nominal`` (1 = as specified); the basis of the dead and dimmed flags.
    residual_rms_before, residual_rms_after : ndarray of shape (M,)
        RMS of measured minus modelled amplitude over each LED's rows, with the nominal and
        the calibrated model; NaN for an LED without rows.
    noise_std : float
        Estimated standard deviation of the amplitude noise (pooled residuals).
    points_per_led : ndarray of shape (M,)
        Survey rows per LED.
    points_in_view : ndarray of shape (M,)
        Of those, rows inside the LED's field of view (the only informative ones).
    dead_leds, dimmed_leds, unsurveyed_leds : tuple of int
        LEDs with no signal (not detected above the noise, or relative amplitude below
        ``dead_below``), with a weak one, and without any row in view.
    converged : bool
        Every per-LED least-squares fit ended on a convergence criterion.
    """

    pilot_amplitudes: FloatArray
    lambertian_orders: FloatArray
    half_power_angles_deg: FloatArray
    receiver_gain: float
    relative_amplitudes: FloatArray
    residual_rms_before: FloatArray
    residual_rms_after: FloatArray
    noise_std: float
    points_per_led: IntArray
    points_in_view: IntArray
    dead_leds: tuple[int, ...]
    dimmed_leds: tuple[int, ...]
    unsurveyed_leds: tuple[int, ...]
    converged: bool

    def to_mapping(self) -> dict[str, Any]:
        """The result as JSON-ready plain values (NaN residuals become None)."""

        return {item.name: _plain(getattr(self, item.name)) for item in fields(self)}


def half_power_angle_deg(order: float | FloatArray) -> FloatArray:
    """Half-power angle from the Lambertian order, ``arccos(2^(-1/m))`` in degrees.

    Examples
    --------
    >>> round(float(half_power_angle_deg(1.0)), 6)
    60.0
    """
    m = np.asarray(order, dtype=np.float64)
    return np.asarray(np.rad2deg(np.arccos(2.0 ** (-1.0 / m))), dtype=np.float64)


def calibrate(
    layout: Layout, survey: Survey, *, dimmed_below: float = 0.5, dead_below: float = 0.1
) -> CalibrationResult:
    """Fit per-LED pilot amplitudes and Lambertian orders (and the receiver gain) to a survey.

    Parameters
    ----------
    layout : Layout
        The nominal room (LED positions, receiver and grid height are taken as exact).
    survey : Survey
        S rows of measured amplitudes.
    dimmed_below : float, default=0.5
        LEDs whose relative amplitude ``x_i / x_i^nominal`` is below this are dimmed.
    dead_below : float, default=0.1
        ... and below this dead (no usable signal).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    MeasurementError
        When an LED index is out of range (``field="led_indices"``), a point lies outside
        the room (``field="points"``) or the thresholds are not
        ``0 <= dead_below <= dimmed_below <= 1``.

    Notes
    -----
    See the module docstring for the model and how the degenerate common scale is fixed.
    The fit is deterministic: no random restarts are needed with the log-linear start.

    Examples
    --------
    >>> from dataclasses import replace
    >>> from app.vlp.presets import paper_layout
    >>> room = paper_layout()
    >>> true = replace(room, leds=tuple(replace(led, half_power_angle_deg=55.0)
    ...                                 for led in room.leds))
    >>> ticks = np.arange(0.25, 4.0, 0.5)
    >>> points = np.array([(x, y) for x in ticks for y in ticks])
    >>> result = calibrate(room, simulate_survey(true, points, 1e-8, rng=0))
    >>> np.round(result.half_power_angles_deg[:3], 1)
    array([55., 55., 55.])
    >>> result.dead_leds, result.dimmed_leds
    ((), ())
    """
    if not 0.0 <= dead_below <= dimmed_below <= 1.0:
        raise MeasurementError(
            f"need 0 <= dead_below <= dimmed_below <= 1, got {dead_below!r} and {dimmed_below!r}",
            field="dimmed_below",
        )
    check_survey(layout, survey)
    n_leds = layout.n_leds
    orders_nominal, _ = led_constants(layout)
    nominal = layout.pilot_amplitudes
    ones = np.ones(n_leds)
    before = rms_per_led(
        survey, survey.amplitudes - model_amplitudes(layout, survey, ones, orders_nominal), n_leds
    )
    ratios, orders = ones.copy(), orders_nominal.copy()
    in_view = np.zeros(n_leds, dtype=np.intp)
    converged = True
    for i in range(n_leds):
        mine = survey.led_indices == i
        rows, _ = led_rows(layout, i, survey.points[mine], survey.amplitudes[mine])
        in_view[i] = rows.amplitudes.size
        if in_view[i]:
            ratios[i], orders[i], ok = fit_led(rows, float(orders_nominal[i]))
            converged = converged and ok
    modelled = model_amplitudes(layout, survey, ratios, orders)
    residuals = survey.amplitudes - modelled
    dof = max(survey.n_rows - 2 * int(np.count_nonzero(in_view)), 1)
    noise_var = float(residuals @ residuals) / dof
    energy = np.bincount(survey.led_indices, weights=modelled**2, minlength=n_leds)
    detected = (energy > 0) & (energy > _DETECTION_SNR * noise_var)
    gain, relative, dead, dimmed = classify(ratios, in_view > 0, detected, dimmed_below, dead_below)
    orders = np.where(dead, orders_nominal, orders)
    return CalibrationResult(
        pilot_amplitudes=np.where(dead, nominal, relative * nominal),
        lambertian_orders=orders,
        half_power_angles_deg=half_power_angle_deg(orders),
        receiver_gain=gain,
        relative_amplitudes=relative,
        residual_rms_before=before,
        residual_rms_after=rms_per_led(survey, residuals, n_leds),
        noise_std=math.sqrt(noise_var),
        points_per_led=np.bincount(survey.led_indices, minlength=n_leds).astype(np.intp),
        points_in_view=in_view,
        dead_leds=_indices(dead),
        dimmed_leds=_indices(dimmed),
        unsurveyed_leds=_indices(in_view == 0),
        converged=converged,
    )


def calibrated_layout(layout: Layout, result: CalibrationResult) -> Layout:
    """The layout with fitted pilot amplitudes and half-power angles, receiver gain folded in.

    LED indices are kept: dead LEDs stay with their nominal parameters (drop them with
    :func:`masked_layout`). The receiver's ``filter_gain`` is multiplied by
    ``result.receiver_gain`` so that ``h x`` of the calibrated layout reproduces the survey
    (valid for terminals whose receivers are like the survey receiver).

    Raises
    ------
    MeasurementError
        When the result does not have one entry per LED of the layout (``field="result"``).
    """
    if result.pilot_amplitudes.shape != (layout.n_leds,):
        raise MeasurementError(
            f"calibration result has {result.pilot_amplitudes.shape[0]} LEDs, the layout "
            f"{layout.n_leds}",
            field="result",
        )
    leds = tuple(
        replace(
            led,
            pilot_amplitude=float(result.pilot_amplitudes[i]),
            half_power_angle_deg=float(result.half_power_angles_deg[i]),
        )
        for i, led in enumerate(layout.leds)
    )
    receiver = replace(
        layout.receiver, filter_gain=layout.receiver.filter_gain * result.receiver_gain
    )
    return replace(layout, leds=leds, receiver=receiver)


def masked_layout(layout: Layout, dead_led_indices: tuple[int, ...] | list[int]) -> Layout:
    """The layout without the given LEDs (their rows of H, J drop out; others keep order).

    Raises
    ------
    MeasurementError
        When an index is out of range or every LED would be dropped
        (``field="dead_leds"``).
    """
    drop = set()
    for index in dead_led_indices:
        if not 0 <= int(index) < layout.n_leds:
            raise MeasurementError(
                f"LED index {index} out of range [0, {layout.n_leds})", field="dead_leds"
            )
        drop.add(int(index))
    kept: tuple[Led, ...] = tuple(led for i, led in enumerate(layout.leds) if i not in drop)
    if not kept:
        raise MeasurementError("cannot drop every LED of the layout", field="dead_leds")
    return replace(layout, leds=kept)


# -- private kernels (inputs already validated) -------------------------------------------------
def _plain(value: object) -> object:
    """Arrays and tuples as lists, non-finite floats as None."""
    if isinstance(value, np.ndarray | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


def _indices(mask: BoolArray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.flatnonzero(mask))
