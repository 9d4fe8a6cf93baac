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
import numpy.typing as npt
from scipy.optimize import least_squares

from ._random import RandomState, as_generator
from ._typing import BoolArray, FloatArray, IntArray
from .channel import channel_gains, lambertian_order, led_constants
from .errors import MeasurementError
from .layout import Layout, Led

__all__ = [
    "CalibrationResult",
    "Survey",
    "calibrate",
    "calibrated_layout",
    "half_power_angle_deg",
    "masked_layout",
    "simulate_survey",
    "survey_from_rows",
]

# Lambertian orders allowed in the fit: half-power angles between 89.5 and 0.5 degrees.
_MIN_ORDER = float(lambertian_order(89.5))
_MAX_ORDER = float(lambertian_order(0.5))
# In-view survey rows needed to fit the order as well as the amplitude.
_MIN_ROWS_FOR_ORDER = 3
# An LED is detected when its fitted signal energy over its rows exceeds this many noise
# variances (a fit of two parameters to pure noise gives about chi-squared with 2 d.o.f.).
_DETECTION_SNR = 25.0


@dataclass(frozen=True)
class Survey:
    """Measured pilot amplitudes at surveyed points, one row per (point, LED) pair.

    Parameters
    ----------
    points : ndarray of shape (S, 2)
        Receiver positions ``(x, y)``, metres, on the receivers' plane.
    led_indices : ndarray of shape (S,)
        Index ``i`` of the LED each amplitude belongs to (0-based, layout order).
    amplitudes : ndarray of shape (S,)
        Measured pilot amplitude ``a`` (same unit as ``h x``; may be slightly negative from
        noise).

    Raises
    ------
    MeasurementError
        On wrong shapes, non-finite values or non-integer LED indices; ``field`` names the
        input (``"points"``, ``"led_indices"``, ``"amplitudes"``).
    """

    points: FloatArray
    led_indices: IntArray
    amplitudes: FloatArray

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] < 1:
            raise MeasurementError(
                f"points must have shape (S, 2) with S >= 1, got {points.shape}", field="points"
            )
        n_rows = points.shape[0]
        raw_indices = np.asarray(self.led_indices)
        amplitudes = np.asarray(self.amplitudes, dtype=np.float64)
        for name, array in (("led_indices", raw_indices), ("amplitudes", amplitudes)):
            if array.shape != (n_rows,):
                raise MeasurementError(
                    f"{name} must have shape ({n_rows},) like points, got {array.shape}", field=name
                )
        _require_finite(points, "points")
        _require_finite(amplitudes, "amplitudes")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "led_indices", _as_indices(raw_indices))
        object.__setattr__(self, "amplitudes", amplitudes)

    @property
    def n_rows(self) -> int:
        """Number of survey rows S."""
        return int(self.amplitudes.shape[0])


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


def survey_from_rows(rows: FloatArray) -> Survey:
    """A :class:`Survey` from rows ``(x, y, led_index, amplitude)``, ndarray of shape (S, 4)."""
    table = np.asarray(rows, dtype=np.float64)
    if table.ndim != 2 or table.shape[1] != 4:
        raise MeasurementError(
            f"survey rows must have shape (S, 4): x, y, led index, amplitude; got {table.shape}",
            field="rows",
        )
    return Survey(points=table[:, :2], led_indices=_as_indices(table[:, 2]), amplitudes=table[:, 3])


def simulate_survey(
    layout: Layout, points: FloatArray, noise_std: float = 0.0, *, rng: RandomState = None
) -> Survey:
    """Survey every LED at every point of a (true) layout, with Gaussian amplitude noise.

    Parameters
    ----------
    layout : Layout
        The true room (perturbed amplitudes and angles as the real LEDs are).
    points : ndarray of shape (P, 2)
        Surveyed positions, metres.
    noise_std : float, default=0.0
        Standard deviation of the additive noise on each amplitude.
    rng : Generator, int or None

    Returns
    -------
    Survey
        S = P * M rows, point-major (rows ``k * M .. k * M + M - 1`` belong to point k).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    clean = channel_gains(layout, pts) * layout.pilot_amplitudes[:, None]  # (M, P)
    noisy = clean + noise_std * as_generator(rng).standard_normal(clean.shape)
    n_leds = layout.n_leds
    return Survey(
        points=np.repeat(pts, n_leds, axis=0),
        led_indices=np.tile(np.arange(n_leds, dtype=np.intp), pts.shape[0]),
        amplitudes=noisy.T.ravel(),
    )


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
    _check_against_layout(layout, survey)
    n_leds = layout.n_leds
    orders_nominal, _ = led_constants(layout)
    nominal = layout.pilot_amplitudes
    ones = np.ones(n_leds)
    before = _rms_per_led(
        survey, survey.amplitudes - _model_amplitudes(layout, survey, ones, orders_nominal), n_leds
    )
    ratios, orders = ones.copy(), orders_nominal.copy()
    in_view = np.zeros(n_leds, dtype=np.intp)
    converged = True
    for i in range(n_leds):
        mine = survey.led_indices == i
        rows, _ = _led_rows(layout, i, survey.points[mine], survey.amplitudes[mine])
        in_view[i] = rows.amplitudes.size
        if in_view[i]:
            ratios[i], orders[i], ok = _fit_led(rows, float(orders_nominal[i]))
            converged = converged and ok
    modelled = _model_amplitudes(layout, survey, ratios, orders)
    residuals = survey.amplitudes - modelled
    dof = max(survey.n_rows - 2 * int(np.count_nonzero(in_view)), 1)
    noise_var = float(residuals @ residuals) / dof
    energy = np.bincount(survey.led_indices, weights=modelled**2, minlength=n_leds)
    detected = (energy > 0) & (energy > _DETECTION_SNR * noise_var)
    gain, relative, dead, dimmed = _classify(
        ratios, in_view > 0, detected, dimmed_below, dead_below
    )
    orders = np.where(dead, orders_nominal, orders)
    return CalibrationResult(
        pilot_amplitudes=np.where(dead, nominal, relative * nominal),
        lambertian_orders=orders,
        half_power_angles_deg=half_power_angle_deg(orders),
        receiver_gain=gain,
        relative_amplitudes=relative,
        residual_rms_before=before,
        residual_rms_after=_rms_per_led(survey, residuals, n_leds),
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
def _require_finite(array: FloatArray, name: str) -> None:
    bad = np.flatnonzero(~np.isfinite(array.reshape(array.shape[0], -1)).all(axis=1))
    if bad.size:
        raise MeasurementError(f"{name} must be finite; row {int(bad[0])} is not", field=name)


def _as_indices(raw: npt.ArrayLike) -> IntArray:
    values = np.asarray(raw, dtype=np.float64)
    _require_finite(values, "led_indices")
    if np.any(values != np.round(values)):
        raise MeasurementError("led_indices must be whole numbers", field="led_indices")
    return values.astype(np.intp)


def _check_against_layout(layout: Layout, survey: Survey) -> None:
    bad = np.flatnonzero((survey.led_indices < 0) | (survey.led_indices >= layout.n_leds))
    if bad.size:
        raise MeasurementError(
            f"led_indices[{int(bad[0])}] = {int(survey.led_indices[bad[0]])} is not an LED "
            f"index in [0, {layout.n_leds})",
            field="led_indices",
        )
    x, y = survey.points[:, 0], survey.points[:, 1]
    outside = np.flatnonzero((x < 0) | (x > layout.room.length) | (y < 0) | (y > layout.room.width))
    if outside.size:
        k = int(outside[0])
        raise MeasurementError(
            f"points[{k}] = ({x[k]!r}, {y[k]!r}) m lies outside the room "
            f"[0, {layout.room.length!r}] x [0, {layout.room.width!r}]",
            field="points",
        )


@dataclass(frozen=True)
class _LedRows:
    """One LED's survey rows inside its field of view, and its model ``r x0 h(p; m)``."""

    log_cos: FloatArray  # ln(dz / d), the cosine of the incidence (= irradiance) angle
    dist_sq: FloatArray  # d^2, m^2
    amplitudes: FloatArray
    base: float  # x_i^nominal A G_f G_c / (2 pi)

    def model(self, ratio: float, order: float) -> FloatArray:
        return np.asarray(
            ratio * self.base * (order + 1.0) * np.exp((order + 1.0) * self.log_cos) / self.dist_sq
        )


def _led_rows(
    layout: Layout, index: int, points: FloatArray, amplitudes: FloatArray
) -> tuple[_LedRows, BoolArray]:
    led = layout.leds[index]
    dz = led.z - layout.grid.receiver_height
    dist_sq = (points[:, 0] - led.x) ** 2 + (points[:, 1] - led.y) ** 2 + dz**2
    cos_inc = dz / np.sqrt(dist_sq)
    view = cos_inc >= math.cos(math.radians(layout.receiver.fov_deg)) - 1e-15
    orders, prefactors = led_constants(layout)
    base = float(layout.pilot_amplitudes[index] * prefactors[index] / (orders[index] + 1.0))
    return _LedRows(np.log(cos_inc[view]), dist_sq[view], amplitudes[view], base), view


def _model_amplitudes(
    layout: Layout, survey: Survey, ratios: FloatArray, orders: FloatArray
) -> FloatArray:
    """``r_i x_i^nominal h(p_k; m_i)`` per survey row; 0 outside the field of view."""
    out = np.zeros(survey.n_rows)
    for i in range(layout.n_leds):
        rows = np.flatnonzero(survey.led_indices == i)
        led_rows, view = _led_rows(layout, i, survey.points[rows], survey.amplitudes[rows])
        out[rows[view]] = led_rows.model(float(ratios[i]), float(orders[i]))
    return out


def _fit_led(rows: _LedRows, nominal_order: float) -> tuple[float, float, bool]:
    """Least-squares ``(r_i, m_i)`` of one LED (``m_i`` nominal when too few rows)."""
    scale = max(
        float(np.max(np.abs(rows.amplitudes))), float(np.max(rows.model(1.0, nominal_order)))
    )
    fit_order = rows.amplitudes.size >= _MIN_ROWS_FOR_ORDER

    def unpack(params: FloatArray) -> tuple[float, float]:
        return float(params[0]), float(params[1]) if fit_order else nominal_order

    def residuals(params: FloatArray) -> FloatArray:
        return np.asarray((rows.model(*unpack(params)) - rows.amplitudes) / scale)

    def jacobian(params: FloatArray) -> FloatArray:
        ratio, order = unpack(params)
        model = rows.model(1.0, order) / scale
        d_order = ratio * model * (1.0 / (order + 1.0) + rows.log_cos)
        return np.column_stack((model, d_order) if fit_order else (model,))

    lower = np.array([0.0, _MIN_ORDER])[: 2 if fit_order else 1]
    upper = np.array([np.inf, _MAX_ORDER])[: lower.size]
    starts = [np.array([1.0, nominal_order]), _log_linear_start(rows)]
    best = None
    for start in (s for s in starts if s is not None):
        x0 = np.clip(start[: lower.size], lower + 1e-12, upper - 1e-12)
        sol = least_squares(
            residuals,
            x0,
            jac=jacobian,
            bounds=(lower, upper),
            method="trf",
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            max_nfev=500,
        )
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    ratio, order = unpack(best.x)
    return ratio, order, bool(best.status > 0)


def _log_linear_start(rows: _LedRows) -> FloatArray | None:
    """Start ``(ratio, m)`` from ``ln a = ln(r base (m+1)) + (m+1) ln cos - ln d^2``."""
    log_cos, dist_sq, meas, base = rows.log_cos, rows.dist_sq, rows.amplitudes, rows.base
    positive = meas > 0.05 * float(np.max(meas)) if np.max(meas) > 0 else meas > 0
    if positive.sum() < 2 or np.ptp(log_cos[positive]) <= 1e-9:
        return None
    target = np.log(meas[positive]) + np.log(dist_sq[positive]) - log_cos[positive]
    design = np.column_stack((np.ones(int(positive.sum())), log_cos[positive]))
    weights = meas[positive] / np.max(meas[positive])  # var(ln a) ~ sigma^2 / a^2
    coef, *_ = np.linalg.lstsq(design * weights[:, None], target * weights, rcond=None)
    order = float(np.clip(coef[1], _MIN_ORDER, _MAX_ORDER))
    return np.array([math.exp(float(coef[0])) / (base * (order + 1.0)), order])


def _classify(
    ratios: FloatArray,
    surveyed: BoolArray,
    detected: BoolArray,
    dimmed_below: float,
    dead_below: float,
) -> tuple[float, FloatArray, BoolArray, BoolArray]:
    """Common gain, relative amplitudes and the dead and dimmed masks."""
    gain = _common_gain(ratios[surveyed & detected], dimmed_below)
    relative = np.where(surveyed, ratios / gain, 1.0)
    dead = surveyed & (~detected | (relative < dead_below))
    dimmed = surveyed & ~dead & (relative < dimmed_below)
    return gain, relative, dead, dimmed


def _common_gain(ratios: FloatArray, dimmed_below: float) -> float:
    """Geometric mean of the per-LED ratios that are not far below their median."""
    if ratios.size == 0 or np.median(ratios) <= 0:
        return 1.0
    healthy = ratios[(ratios > 0) & (ratios >= dimmed_below * float(np.median(ratios)))]
    return float(np.exp(np.mean(np.log(healthy))))


def _rms_per_led(survey: Survey, residuals: FloatArray, n_leds: int) -> FloatArray:
    counts = np.bincount(survey.led_indices, minlength=n_leds)
    sums = np.bincount(survey.led_indices, weights=residuals**2, minlength=n_leds)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan))


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
