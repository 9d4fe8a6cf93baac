"""The calibration step of a ``calibration`` job, run in the build child before the build.

From the room's nominal layout and the job's payload (the stored request and, for a request
without a survey, the calibration it re-uses) it produces the calibrated layout, the layout
to build (calibrated, masked LEDs dropped), the final mask and the report. Plain JSON values
in and out: the outcome is stored as it is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.vlp.calibration import (
    SURFACE_NAMES,
    CalibrationResult,
    calibrate,
    calibrated_layout,
    masked_layout,
)
from app.vlp.channel import lambertian_order
from app.vlp.layout import Layout
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.survey import survey_from_rows

__all__ = ["apply_calibration"]


def apply_calibration(nominal: Layout, payload: dict[str, Any]) -> dict[str, Any]:
    """Fit (or re-use a fit), mask, and describe the result.

    Parameters
    ----------
    nominal : Layout
        The room's layout as the admin wrote it (M LEDs).
    payload : dict
        ``{"request": {...}, "base": None | {"id", "calibrated_layout", "report"}}``; the
        request has ``survey`` (rows ``[x, y, led, amplitude]``, may be empty),
        ``masked_leds``, ``mask_dead_leds``, ``dimmed_below``, ``dead_below`` and, in
        requests stored since they exist, ``led_position_bound_m``, ``led_tilt_bound_deg``,
        ``fit_reflectance``, ``fit_beams``, ``fit_gain_map`` and ``apply_receiver_gain``
        (absent: no position fit, no normal fit, no reflectance fit, no beam fit, no gain map,
        gain folded in, as the requests stored before them were fitted). A survey amplitude
        None (JSON null) is a row whose LED was not detected.

    Returns
    -------
    dict
        ``report`` (JSON), ``calibrated_layout`` and ``layout`` (layout mappings; ``layout``
        has the masked LEDs dropped) and ``masked_leds`` (sorted room LED indices).

    Raises
    ------
    app.vlp.errors.MeasurementError
        When the survey does not fit the layout or every LED would be masked.
    """
    request = payload["request"]
    survey_rows = request.get("survey") or []
    base = payload.get("base")
    if survey_rows:
        result = calibrate(
            nominal,
            survey_from_rows(np.asarray(survey_rows, dtype=np.float64)),
            dimmed_below=float(request.get("dimmed_below", 0.75)),
            dead_below=float(request.get("dead_below", 0.1)),
            led_position_bound_m=float(request.get("led_position_bound_m", 0.0)),
            led_tilt_bound_deg=float(request.get("led_tilt_bound_deg", 0.0)),
            fit_reflectance=bool(request.get("fit_reflectance", False)),
            fit_beams=bool(request.get("fit_beams", False)),
            fit_gain_map=bool(request.get("fit_gain_map", False)),
        )
        calibrated = calibrated_layout(
            nominal, result, apply_receiver_gain=bool(request.get("apply_receiver_gain", True))
        )
        report = _report(nominal, result, len(survey_rows))
    elif base is not None:
        calibrated = layout_from_mapping(base["calibrated_layout"])
        report = {**base["report"], "survey_rows": 0}
    else:
        calibrated = nominal
        report = _nominal_report(nominal)
    if survey_rows:
        error = calibrated.amplitude_error
        report["amplitude_error"] = None if error is None else error.to_mapping()
        report["gain_map"] = _gain_map_report(result)
    masked = set(int(i) for i in request.get("masked_leds") or ())
    if request.get("mask_dead_leds", True):
        masked |= {led["index"] for led in report["leds"] if led["flag"] == "dead"}
    order = sorted(masked)
    for led in report["leds"]:
        led["masked"] = led["index"] in masked
    return {
        "report": report,
        "calibrated_layout": calibrated.to_mapping(),
        "layout": masked_layout(calibrated, order).to_mapping(),
        "masked_leds": order,
    }


def _gain_map_report(result: CalibrationResult) -> dict[str, Any] | None:
    gain_map = result.gain_map
    if gain_map is None:
        return None
    return {
        "length_scale_m": gain_map.length_scale_m,
        "leds": list(gain_map.mapped_leds),
        "evidence": float(result.gain_map_evidence),
    }


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _beam(result: CalibrationResult, nominal: Layout, index: int) -> dict[str, Any] | None:
    beam = result.beams[index] if result.beams else nominal.leds[index].beam
    return None if beam is None else beam.to_mapping()


def _report(nominal: Layout, result: CalibrationResult, n_rows: int) -> dict[str, Any]:
    """The fit per LED, with a flag ``ok``/``dimmed``/``dead``/``unsurveyed``."""
    flags = {i: "dimmed" for i in result.dimmed_leds}
    flags.update({i: "unsurveyed" for i in result.unsurveyed_leds})
    flags.update({i: "dead" for i in result.dead_leds})
    orders_nominal = lambertian_order(nominal.half_power_angles_deg)
    leds = [
        {
            "index": i,
            "flag": flags.get(i, "ok"),
            "pilot_amplitude": float(result.pilot_amplitudes[i]),
            "nominal_pilot_amplitude": float(nominal.leds[i].pilot_amplitude),
            "relative_amplitude": float(result.relative_amplitudes[i]),
            "lambertian_order": float(result.lambertian_orders[i]),
            "nominal_lambertian_order": float(orders_nominal[i]),
            "half_power_angle_deg": float(result.half_power_angles_deg[i]),
            "residual_rms_before": _number(float(result.residual_rms_before[i])),
            "residual_rms_after": _number(float(result.residual_rms_after[i])),
            "survey_points": int(result.points_per_led[i]),
            "points_in_view": int(result.points_in_view[i]),
            "masked": False,
            "x": float(result.led_positions[i, 0]),
            "y": float(result.led_positions[i, 1]),
            "nominal_x": float(nominal.leds[i].x),
            "nominal_y": float(nominal.leds[i].y),
            "shift_m": float(np.hypot(*result.led_shifts_m[i])),
            "normal": [float(v) for v in result.led_normals[i]],
            "tilt_deg": float(result.tilts_deg[i]),
            "tilt_azimuth_deg": float(result.tilt_azimuths_deg[i]),
            "beam": _beam(result, nominal, i),
        }
        for i in range(nominal.n_leds)
    ]
    fitted = np.isfinite(result.reflectance_sd)
    return {
        "survey_rows": n_rows,
        "receiver_gain": float(result.receiver_gain),
        "noise_std": _number(float(result.noise_std)),
        "converged": bool(result.converged),
        "leds": leds,
        "reflectance": None if result.reflectance is None else result.reflectance.to_mapping(),
        "reflectance_sd": (
            {
                name: _number(float(result.reflectance_sd[s])) if fitted[s] else None
                for s, name in enumerate(SURFACE_NAMES)
            }
            if fitted.any()
            else None
        ),
    }


def _normal_report(normal: tuple[float, float, float]) -> dict[str, Any]:
    """``normal``, ``tilt_deg`` and ``tilt_azimuth_deg`` of a layout's LED normal."""
    nx, ny, nz = normal
    flat = math.hypot(nx, ny) <= 1e-12
    return {
        "normal": [nx, ny, nz],
        "tilt_deg": math.degrees(math.acos(max(-1.0, min(1.0, -nz)))),
        "tilt_azimuth_deg": 0.0 if flat else math.degrees(math.atan2(ny, nx)) % 360.0,
    }


def _nominal_report(nominal: Layout) -> dict[str, Any]:
    """The report of a room never calibrated: its nominal model, every LED unsurveyed."""
    # The orders the layout states (an LED with a beam has order 0 in the channel).
    angles = nominal.half_power_angles_deg
    orders = lambertian_order(angles)
    leds = [
        {
            "index": i,
            "flag": "unsurveyed",
            "pilot_amplitude": float(led.pilot_amplitude),
            "nominal_pilot_amplitude": float(led.pilot_amplitude),
            "relative_amplitude": 1.0,
            "lambertian_order": float(orders[i]),
            "nominal_lambertian_order": float(orders[i]),
            "half_power_angle_deg": float(angles[i]),
            "residual_rms_before": None,
            "residual_rms_after": None,
            "survey_points": 0,
            "points_in_view": 0,
            "masked": False,
            "x": float(led.x),
            "y": float(led.y),
            "nominal_x": float(led.x),
            "nominal_y": float(led.y),
            "shift_m": 0.0,
            **_normal_report(led.normal),
            "beam": None if led.beam is None else led.beam.to_mapping(),
        }
        for i, led in enumerate(nominal.leds)
    ]
    reflectance = nominal.room.reflectance
    return {
        "survey_rows": 0,
        "receiver_gain": 1.0,
        "noise_std": None,
        "converged": True,
        "leds": leds,
        "reflectance": None if reflectance is None else reflectance.to_mapping(),
        "reflectance_sd": None,
    }
