"""Survey calibration: fit each LED's pilot amplitude, Lambertian order, x, y and normal (and
the surfaces' reflectances) to measured amplitudes.

The paper assumes the channel information is "collected via beforehand channel estimation
indoors". An admin walks a receiver over surveyed points ``p_k`` (on the receivers' plane) and
records, per LED ``i``, the received pilot amplitude ``a_k``. The model (``channel.py``,
``reflections.py``) is

.. math::

    a_k = g\\, x_i \\big(h(p_k; m_i, s_i) + \\sum_j \\rho_j D_{ij}(p_k)\\big) + n_k, \\qquad
    h(p; m, s) = \\frac{(m+1) A G_f G_c}{2 \\pi} \\frac{dz^{m+1}}{d^{m+3}} \\ (\\phi \\le FOV),

with ``x_i`` the pilot amplitude, ``m_i`` the Lambertian order, ``s_i`` the LED's ``(x, y)``
(``d`` its distance to ``p``; for a tilted LED of normal ``n_i`` the factor ``dz^m`` becomes
``(n_i . (p - s_i))^m``, :mod:`app.vlp.channel`), ``g`` the receiver's gain relative to the
nominal receiver of the layout, and ``D_ij`` the first diffuse bounce off surface ``j``
(walls, floor, ceiling) per unit reflectance ``rho_j``, computed once with the nominal LEDs (a
shift of a few centimetres or degrees changes the reflected part, a fraction of the signal,
to second order). Without ``room.reflectance`` and without ``fit_reflectance`` the sum is absent.

Identifiability and the choice made here: only the products ``r_i = g x_i / x_i^nominal``
can be told apart from amplitudes, so the fit is done on ``(r_i, m_i, s_i, n_i)``. With the
reflectances fixed (the layout's) it separates into M independent problems of up to six
parameters (each LED's rows depend only on its own), solved by
``scipy.optimize.least_squares`` with bounds (``s_i`` within ``led_position_bound_m`` of the
layout's, ``n_i`` within ``led_tilt_bound_deg`` of the layout's normal), started from a
log-linear fit and from the nominal values (the lower cost wins). Rows whose LED was not
detected (NaN amplitudes, ``null`` in the API) are censored below the survey's detection
floor: they cost the model's excess over the floor, nothing while the model stays below it.
With ``fit_reflectance`` the reflectances that the survey can see are then fitted jointly with
every LED (sparse Jacobian), and their standard deviations come from the Schur complement of
the Fisher information. The products are split into one receiver gain ``g`` and per-LED
``x_i`` by fixing the geometric mean of ``x_i / x_i^nominal`` over the healthy LEDs to 1:
``g`` is that geometric mean of the ``r_i``, so a survey receiver that is uniformly
more or less sensitive than the nominal one is not mistaken for dimmed LEDs. LEDs whose
relative amplitude ``x_i / x_i^nominal`` is below ``dead_below`` are reported dead, below
``dimmed_below`` dimmed. :func:`calibrated_layout` folds ``g`` into the receiver's
``filter_gain``, so the calibrated model reproduces the surveyed amplitudes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ._calibration_beams import MIN_ROWS_FOR_BEAM, measured_beam, with_beam
from ._calibration_fit import (
    MIN_ROWS_FOR_POSITION,
    MIN_ROWS_FOR_TILT,
    SURFACE_NAMES,
    LedFit,
    LedRows,
    classify,
    diffuse_rows,
    fit_jointly,
    fit_led,
    identifiable_surfaces,
    led_rows,
    rms_per_led,
)
from ._calibration_scatter import survey_scatter
from ._reflection_table import ReflectionTable
from .channel import lambertian_order, led_constants
from .errors import MeasurementError, ProblemSizeError
from .gain_map import GainMap, GainMapFit, fit_gain_map
from .layout import AmplitudeError, Beam, Layout, Led, Reflectance
from .survey import Survey, check_survey, simulate_survey, survey_from_rows
from .typing import BoolArray, FloatArray, IntArray

__all__ = [
    "DEFAULT_LED_POSITION_BOUND_M",
    "DEFAULT_LED_TILT_BOUND_DEG",
    "MIN_ROWS_FOR_BEAM",
    "MIN_ROWS_FOR_POSITION",
    "MIN_ROWS_FOR_TILT",
    "SURFACE_NAMES",
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
# How far (metres, in x and in y) a fitted LED may move from the layout's position: fittings
# are placed to a few centimetres, a wrong drawing or a swapped fitting is further off.
DEFAULT_LED_POSITION_BOUND_M = 0.3
# How far (degrees) a fitted LED normal may turn from the layout's: fixtures hang within a few
# degrees of their drawing; a face turned further is no longer a small tilt of the same beam.
DEFAULT_LED_TILT_BOUND_DEG = 15.0
MAX_LED_TILT_BOUND_DEG = 45.0
# Where a fitted reflectance starts when the layout gives none (the lighting-design default
# for walls, docs/explanation/real-rooms.md#the-simulators-true-channel).
_REFLECTANCE_START = 0.5


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
    led_positions : ndarray of shape (M, 2), metres
        Fitted ``(x, y)`` of each LED (the layout's for dead LEDs and LEDs with fewer than
        :data:`MIN_ROWS_FOR_POSITION` rows in view).
    led_shifts_m : ndarray of shape (M, 2), metres
        ``led_positions`` minus the layout's.
    reflectance : Reflectance or None
        The surfaces' reflectance of the calibrated model: fitted when asked (surfaces the
        survey cannot see keep the layout's value, or 0), else the layout's.
    reflectance_sd : ndarray of shape (3,)
        Standard deviation of each fitted reflectance (walls, floor, ceiling) from the fit's
        Fisher information with every LED parameter free; NaN where not fitted.
    led_normals : ndarray of shape (M, 3)
        Fitted unit normal of each LED's face (the layout's where not fitted).
    tilts_deg : ndarray of shape (M,), degrees
        Angle between each fitted normal and straight down.
    tilt_azimuths_deg : ndarray of shape (M,), degrees in [0, 360)
        Direction its face turns to, counter-clockwise from +x (0 for an untilted LED).
    amplitude_error : AmplitudeError or None
        How the survey's detected amplitudes scatter around the calibrated model (its noise,
        its relative error and its tails, :func:`~._calibration_scatter.survey_scatter`); None
        when the survey leaves no degree of freedom for it. With a gain map, each row's
        scatter is taken around the map fitted without that row (what a point off the survey
        sees).
    gain_map : GainMap or None
        What the survey shows of each LED's gain beyond its model, over the floor
        (:mod:`~app.vlp.gain_map`); None when not asked, when the survey does not show one, or
        in a room too large for its table.
    gain_map_evidence : float
        The map's log marginal likelihood over the model alone (nats; NaN when not asked or
        the room is too large for a map).
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
    led_positions: FloatArray
    led_shifts_m: FloatArray
    reflectance: Reflectance | None
    reflectance_sd: FloatArray
    led_normals: FloatArray
    tilts_deg: FloatArray
    tilt_azimuths_deg: FloatArray
    amplitude_error: AmplitudeError | None = None
    beams: tuple[Beam | None, ...] = ()
    gain_map: GainMap | None = None
    gain_map_evidence: float = math.nan

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
    layout: Layout,
    survey: Survey,
    *,
    dimmed_below: float = 0.5,
    dead_below: float = 0.1,
    led_position_bound_m: float = DEFAULT_LED_POSITION_BOUND_M,
    fit_reflectance: bool = False,
    led_tilt_bound_deg: float = DEFAULT_LED_TILT_BOUND_DEG,
    fit_beams: bool = False,
    fit_gain_map: bool = False,
) -> CalibrationResult:
    """Fit per-LED pilot amplitudes, Lambertian orders, ``x, y`` and normals (and the receiver
    gain, and optionally the surfaces' reflectances) to a survey.

    Parameters
    ----------
    layout : Layout
        The nominal room (LED heights, receiver and grid height are taken as exact; its
        ``room.reflectance``, when set, is the reflected part of the model).
    survey : Survey
        S rows of measured amplitudes.
    dimmed_below : float, default=0.5
        LEDs whose relative amplitude ``x_i / x_i^nominal`` is below this are dimmed.
    dead_below : float, default=0.1
        ... and below this dead (no usable signal).
    led_position_bound_m : float, default=0.3
        Each LED's ``x`` and ``y`` are fitted within this many metres of the layout's (0: kept
        as in the layout). Needs :data:`MIN_ROWS_FOR_POSITION` rows in the LED's view.
    fit_reflectance : bool, default=False
        Also fit the reflectance of every surface whose first-bounce reflection reaches the
        survey's receivers (others keep the layout's value, or 0), jointly with all LEDs.
    led_tilt_bound_deg : float, default=15
        Each LED's normal is fitted within this many degrees of the layout's (0: kept as in
        the layout). Needs :data:`MIN_ROWS_FOR_TILT` detected rows in the LED's view.
    fit_beams : bool, default=False
        Also measure each LED's beam where the survey tells it from a Lambertian one
        (:func:`~app.vlp._calibration_beams.measured_beam`; needs
        :data:`MIN_ROWS_FOR_BEAM` detected rows in view), then fit the LED again with it.
        LEDs whose layout gives a beam keep it.
    fit_gain_map : bool, default=False
        Last, fit the map of what the survey shows of each LED's gain beyond the fitted model
        (:func:`~app.vlp.gain_map.fit_gain_map`; kept only where the survey shows one).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    MeasurementError
        When an LED index is out of range (``field="led_indices"``), a point lies outside
        the room (``field="points"``), the thresholds are not
        ``0 <= dead_below <= dimmed_below <= 1``, the position bound is not in [0, 1] m or
        the tilt bound not in [0, 45] degrees.

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
    if not (math.isfinite(led_position_bound_m) and 0.0 <= led_position_bound_m <= 1.0):
        raise MeasurementError(
            f"led_position_bound_m must be in [0, 1] m, got {led_position_bound_m!r}",
            field="led_position_bound_m",
        )
    if not (
        math.isfinite(led_tilt_bound_deg) and 0.0 <= led_tilt_bound_deg <= MAX_LED_TILT_BOUND_DEG
    ):
        raise MeasurementError(
            f"led_tilt_bound_deg must be in [0, {MAX_LED_TILT_BOUND_DEG:g}] degrees, got "
            f"{led_tilt_bound_deg!r}",
            field="led_tilt_bound_deg",
        )
    check_survey(layout, survey)
    n_leds = layout.n_leds
    orders_nominal, _ = led_constants(layout)
    nominal = layout.pilot_amplitudes
    given = layout.room.reflectance
    rho = np.array([getattr(given, n) if given else 0.0 for n in SURFACE_NAMES])
    reflected = given is not None or fit_reflectance
    groups = [np.flatnonzero(survey.led_indices == i) for i in range(n_leds)]
    per_row = diffuse_rows(layout, survey) if reflected else None
    fitted_surfaces = np.zeros(len(SURFACE_NAMES), dtype=bool)
    if fit_reflectance:
        fitted_surfaces = identifiable_surfaces(_rows(layout, survey, groups, per_row, 0.0))
        rho = np.where(fitted_surfaces & (rho == 0.0), _REFLECTANCE_START, rho)
    before = _model(
        _rows(layout, survey, groups, per_row, 0.0),
        groups,
        survey.n_rows,
        _nominal_fits(orders_nominal),
        rho,
    )
    bounds = (led_position_bound_m, led_tilt_bound_deg)
    rows, fits, rho_fit, rho_sd, converged = _fit_all(
        layout, survey, groups, per_row, rho, fitted_surfaces, bounds
    )
    if per_row is not None and any(np.any(f.free) for f in fits):
        # The reflected part was computed with the nominal LEDs: once more with the fitted
        # positions and beams (a displaced LED lights the walls differently).
        per_row = diffuse_rows(_refreshed(layout, rows, fits), survey)
        rows, fits, rho_fit, rho_sd, converged = _fit_all(
            layout, survey, groups, per_row, rho_fit, fitted_surfaces, bounds
        )
    rho = rho_fit
    # LEDs whose layout gives a beam report the Lambertian order their layout states.
    stated = np.atleast_1d(lambertian_order(layout.half_power_angles_deg))
    beam_given = np.array([b is not None for b in layout.beams])
    lambertian_orders = np.where(beam_given, stated, np.array([f.order for f in fits]))
    beams = list(layout.beams)
    if fit_beams:
        for i, (r, f) in enumerate(zip(rows, fits, strict=True)):
            beam = measured_beam(r, f, rho) if np.any(r.in_view()) else None
            if beam is not None:
                rows[i] = with_beam(r, beam)
                fits[i] = fit_led(rows[i], 0.0, rho, led_position_bound_m)
                beams[i] = beam
    in_view = np.array([int(np.count_nonzero(r.in_view())) for r in rows], dtype=np.intp)
    ratios = np.array([f.ratio for f in fits])
    # An LED given a beam reports the Lambertian order that its beam replaced.
    beamed = np.array([b is not None for b in beams])
    orders = np.where(beamed, lambertian_orders, np.array([f.order for f in fits]))
    orders_nominal = np.where(beam_given, stated, orders_nominal)
    shifts = np.array([f.shift for f in fits]).reshape(n_leds, 2)
    modelled = _model(rows, groups, survey.n_rows, fits, rho)
    residuals = _measured_minus_model(survey, modelled)
    n_params = sum(int(np.count_nonzero(f.free)) for f, v in zip(fits, in_view, strict=True) if v)
    n_detected = int(np.count_nonzero(survey.detected))
    dof = max(n_detected - n_params - int(fitted_surfaces.sum()), 1)
    noise_var = float(residuals @ residuals) / dof
    energy = np.bincount(survey.led_indices, weights=modelled**2, minlength=n_leds)
    detected = (energy > 0) & (energy > _DETECTION_SNR * noise_var)
    gain, relative, dead, dimmed = classify(ratios, in_view > 0, detected, dimmed_below, dead_below)
    orders = np.where(dead, orders_nominal, orders)
    shifts = np.where(dead[:, None], 0.0, shifts)
    normals = np.array([r.normal_at(f.tilt)[0] for r, f in zip(rows, fits, strict=True)])
    normals = np.where(dead[:, None], layout.led_normals, normals)
    beams = [layout.leds[i].beam if dead[i] else b for i, b in enumerate(beams)]
    mapped = _gain_map(layout, survey, modelled, dead) if fit_gain_map else None
    scattered = modelled
    if mapped is not None and mapped.gain_map is not None:
        scattered = modelled * np.exp(mapped.held_out)
    return CalibrationResult(
        pilot_amplitudes=np.where(dead, nominal, relative * nominal),
        lambertian_orders=orders,
        half_power_angles_deg=half_power_angle_deg(orders),
        receiver_gain=gain,
        relative_amplitudes=relative,
        residual_rms_before=rms_per_led(survey, _measured_minus_model(survey, before), n_leds),
        residual_rms_after=rms_per_led(survey, residuals, n_leds),
        noise_std=math.sqrt(noise_var),
        points_per_led=np.bincount(survey.led_indices, minlength=n_leds).astype(np.intp),
        points_in_view=in_view,
        dead_leds=_indices(dead),
        dimmed_leds=_indices(dimmed),
        unsurveyed_leds=_indices(in_view == 0),
        converged=converged,
        led_positions=layout.led_positions[:, :2] + shifts,
        led_shifts_m=shifts,
        reflectance=(
            None
            if not reflected
            else Reflectance(**{n: float(rho[s]) for s, n in enumerate(SURFACE_NAMES)})
        ),
        reflectance_sd=rho_sd,
        led_normals=normals,
        tilts_deg=np.rad2deg(np.arccos(np.clip(-normals[:, 2], -1.0, 1.0))),
        tilt_azimuths_deg=_azimuths_deg(normals),
        amplitude_error=survey_scatter(survey, scattered, n_params),
        beams=tuple(beams),
        gain_map=None if mapped is None else mapped.gain_map,
        gain_map_evidence=math.nan if mapped is None else mapped.evidence,
    )


def _gain_map(
    layout: Layout, survey: Survey, modelled: FloatArray, dead: BoolArray
) -> GainMapFit | None:
    """The map of the detected rows' log residuals (dead LEDs left out); None in a room too
    large for the table that carries it off the grid."""
    try:
        ReflectionTable.check_size(layout)
    except ProblemSizeError:
        return None
    amplitudes = survey.amplitudes
    used = survey.detected & (modelled > 0.0) & (amplitudes > 0.0) & ~dead[survey.led_indices]
    log_residuals = np.full(survey.n_rows, np.nan)
    log_residuals[used] = np.log(amplitudes[used] / modelled[used])
    return fit_gain_map(survey.points, survey.led_indices, log_residuals, layout.n_leds)


def calibrated_layout(
    layout: Layout, result: CalibrationResult, *, apply_receiver_gain: bool = True
) -> Layout:
    """The layout with fitted pilot amplitudes, half-power angles, LED ``x, y``, normals and
    reflectances, receiver gain folded in.

    LED indices are kept: dead LEDs stay with their nominal parameters (drop them with
    :func:`masked_layout`). With ``apply_receiver_gain`` the receiver's ``filter_gain`` is
    multiplied by ``result.receiver_gain`` so that ``h x`` of the calibrated layout
    reproduces the survey (right for terminals whose receivers are like the survey
    receiver, and when the layout's absolute scale is unknown). Without it the model keeps
    the layout's receiver: the fingerprint does not depend on the survey receiver's gain,
    so a survey made with a receiver whose gain drifted gives the same fingerprint (the
    geometric mean of the relative amplitudes is 1 either way).

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
    upper = np.array([layout.room.length, layout.room.width])
    where = np.clip(result.led_positions, 0.0, upper)
    leds = tuple(
        replace(
            led,
            x=float(where[i, 0]),
            y=float(where[i, 1]),
            pilot_amplitude=float(result.pilot_amplitudes[i]),
            half_power_angle_deg=float(result.half_power_angles_deg[i]),
            normal=_normal_tuple(result.led_normals[i]),
            beam=result.beams[i] if result.beams else led.beam,
        )
        for i, led in enumerate(layout.leds)
    )
    gain = result.receiver_gain if apply_receiver_gain else 1.0
    receiver = replace(layout.receiver, filter_gain=layout.receiver.filter_gain * gain)
    room = replace(layout.room, reflectance=result.reflectance)
    error = result.amplitude_error
    if error is not None and not apply_receiver_gain:
        # The survey's noise in the units of a model without the survey receiver's gain.
        error = replace(error, noise_sd=error.noise_sd / result.receiver_gain)
    return replace(
        layout,
        room=room,
        leds=leds,
        receiver=receiver,
        amplitude_error=error,
        gain_map=result.gain_map,
    )


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
    gain_map = None if layout.gain_map is None else layout.gain_map.without_leds(drop)
    return replace(layout, leds=kept, gain_map=gain_map)


# -- private kernels (inputs already validated) -------------------------------------------------
def _plain(value: object) -> object:
    """Arrays and tuples as lists, non-finite floats as None."""
    if isinstance(value, Reflectance | AmplitudeError | Beam | GainMap):
        return value.to_mapping()
    if isinstance(value, np.ndarray | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    return value


def _indices(mask: BoolArray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.flatnonzero(mask))


def _rows(
    layout: Layout,
    survey: Survey,
    groups: list[IntArray],
    per_row: FloatArray | None,
    tilt_bound_deg: float,
) -> list[LedRows]:
    floor = survey.floor
    return [
        led_rows(
            layout,
            i,
            survey.points[g],
            survey.amplitudes[g],
            None if per_row is None else per_row[g],
            tilt_bound_deg=tilt_bound_deg,
            floor=floor,
        )
        for i, g in enumerate(groups)
    ]


def _measured_minus_model(survey: Survey, modelled: FloatArray) -> FloatArray:
    """Residuals per row; a censored row's is minus the model's excess over the floor."""
    detected = survey.detected
    return np.where(
        detected,
        np.where(detected, survey.amplitudes, 0.0) - modelled,
        -np.maximum(modelled - survey.floor, 0.0),
    )


def _azimuths_deg(normals: FloatArray) -> FloatArray:
    """Direction of each normal's horizontal part, degrees in [0, 360) (0 when vertical)."""
    flat = np.hypot(normals[:, 0], normals[:, 1]) <= 1e-12
    angles = np.rad2deg(np.arctan2(normals[:, 1], normals[:, 0])) % 360.0
    return np.asarray(np.where(flat, 0.0, angles))


def _normal_tuple(normal: FloatArray) -> tuple[float, float, float]:
    """A normal as the layout keeps it (exactly straight down when it is, to the last bit)."""
    if np.hypot(normal[0], normal[1]) <= 1e-15:
        return (0.0, 0.0, -1.0)
    return (float(normal[0]), float(normal[1]), float(normal[2]))


def _fit_all(
    layout: Layout,
    survey: Survey,
    groups: list[IntArray],
    per_row: FloatArray | None,
    rho: FloatArray,
    fitted_surfaces: BoolArray,
    bounds: tuple[float, float],
) -> tuple[list[LedRows], list[LedFit], FloatArray, FloatArray, bool]:
    """Each LED alone with ``rho`` fixed, then (when surfaces are fitted) all jointly;
    ``bounds``: the position's (m) and the tilt's (degrees)."""
    bound, tilt_bound = bounds
    orders_nominal, _ = led_constants(layout)
    rows = _rows(layout, survey, groups, per_row, tilt_bound)
    fits = _nominal_fits(orders_nominal)
    live = [i for i, r in enumerate(rows) if np.any(r.in_view())]
    for i in live:
        fits[i] = fit_led(rows[i], float(orders_nominal[i]), rho, bound)
    converged = all(f.converged for f in fits)
    rho_sd = np.full(len(SURFACE_NAMES), np.nan)
    if fitted_surfaces.any() and live:
        joint = fit_jointly(
            [rows[i] for i in live], [fits[i] for i in live], rho, fitted_surfaces, bound
        )
        for i, f in zip(live, joint.leds, strict=True):
            fits[i] = f
        rho, rho_sd, converged = joint.rho, joint.rho_sd, converged and joint.converged
    return rows, fits, rho, rho_sd, converged


def _refreshed(layout: Layout, rows: list[LedRows], fits: list[LedFit]) -> Layout:
    """The layout with the fitted LED positions, beams and normals (nominal pilots: the
    ratios multiply the reflected part as they do the direct one)."""
    upper = np.array([layout.room.length, layout.room.width])
    leds = []
    for led, r, fit in zip(layout.leds, rows, fits, strict=True):
        usable = fit.ratio > 0 and math.isfinite(fit.order)
        if not usable:
            leds.append(led)
            continue
        x, y = np.clip(np.array([led.x, led.y]) + fit.shift, 0.0, upper)
        # An LED with a beam has order 0 in the fit: its stated angle stays.
        angle = led.half_power_angle_deg if led.beam else float(half_power_angle_deg(fit.order))
        normal = _normal_tuple(r.normal_at(fit.tilt)[0])
        leds.append(replace(led, x=float(x), y=float(y), half_power_angle_deg=angle, normal=normal))
    return replace(layout, leds=tuple(leds))


def _nominal_fits(orders: FloatArray) -> list[LedFit]:
    return [LedFit(1.0, float(m), np.zeros(2), (False,) * 6) for m in orders]


def _model(
    rows: list[LedRows], groups: list[IntArray], n_rows: int, fits: list[LedFit], rho: FloatArray
) -> FloatArray:
    """The modelled amplitude of every survey row (survey order)."""
    out = np.zeros(n_rows)
    for r, g, f in zip(rows, groups, fits, strict=True):
        out[g] = r.model(f.ratio, f.order, f.shift, rho, f.tilt)
    return out
