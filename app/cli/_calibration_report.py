"""The readable form of a calibration report (``vlp rooms calibrate`` without ``--json``)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.schemas import Calibration

    from ._output import Output

__all__ = ["show_calibration"]

_COLUMNS = [
    "LED",
    "flag",
    "masked",
    "amplitude / nominal",
    "order (nominal)",
    "half-power (deg)",
    "RMS residual before",
    "after",
    "points in view",
]


def _number(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def show_calibration(out: Output, report: dict[str, Any]) -> None:
    """A summary line and one table row per LED (flagged LEDs first)."""
    from app.schemas import Calibration

    calibration: Calibration = Calibration.model_validate(report)
    leds = calibration.leds or []
    flagged = [led for led in leds if led.flag != "ok" or led.masked]
    out.console.print(
        f"calibration {calibration.id}: {calibration.status}"
        f"{'' if calibration.error is None else f' ({calibration.error})'}; "
        f"{calibration.survey_rows} survey rows; fingerprint version "
        f"{calibration.fingerprint_version if calibration.fingerprint_version else '-'}",
        markup=False,
    )
    if not leds:
        return
    out.console.print(
        f"LEDs flagged: {', '.join(f'{led.index} {led.flag}' for led in flagged) or 'none'}; "
        f"masked: {calibration.masked_leds or 'none'}; receiver gain "
        f"{_number(calibration.receiver_gain, '.3g')}; noise std "
        f"{_number(calibration.noise_std, '.3g')}",
        markup=False,
    )
    ordered = flagged + [led for led in leds if led not in flagged]
    rows = [
        [
            led.index,
            led.flag,
            "yes" if led.masked else "no",
            f"{led.relative_amplitude:.3f}",
            f"{led.lambertian_order:.2f} ({led.nominal_lambertian_order:.2f})",
            f"{led.half_power_angle_deg:.1f}",
            _number(led.residual_rms_before, ".3g"),
            _number(led.residual_rms_after, ".3g"),
            led.points_in_view,
        ]
        for led in ordered
    ]
    out.table("per LED (flagged first)", _COLUMNS, rows)
