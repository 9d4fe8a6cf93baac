"""Survey calibrations: the request (survey rows, mask) and the report per LED."""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field

from ._common import FiniteFloat, RequestInt, RequestModel, ResponseModel, lazy_examples

# No layout has more LEDs than this (the schema's own cap; the service's limit is lower).
MAX_LED_INDEX = 1_000_000

__all__ = [
    "MAX_SURVEY_ROWS",
    "Calibration",
    "CalibrationCreate",
    "CalibrationsList",
    "LedCalibration",
    "SurveyRow",
    "calibration_example",
]

MAX_SURVEY_ROWS = 200_000
LedFlag = Literal["ok", "dimmed", "dead", "unsurveyed"]


def calibration_example() -> dict[str, Any]:
    """A survey of the paper room (16 LEDs) on a 1 m grid of 16 points: LED 5 dimmed to half,
    LED 10 dead, every beam a little narrower (55 degrees) than the layout's 60.

    Amplitudes are noiseless ``h x`` of that perturbed room, rounded to 4 digits. The
    science core is imported here so that importing the schemas does not load numpy.
    """
    import numpy as np

    from app.vlp.calibration import simulate_survey
    from app.vlp.presets import paper_layout

    room = paper_layout()
    leds = tuple(
        replace(
            led,
            half_power_angle_deg=55.0,
            pilot_amplitude={5: 0.5, 10: 1e-9}.get(i, led.pilot_amplitude),
        )
        for i, led in enumerate(room.leds)
    )
    ticks = np.arange(0.5, 4.0, 1.0)
    points = np.array([(x, y) for x in ticks for y in ticks])
    survey = simulate_survey(replace(room, leds=leds), points)
    return {
        "survey": [
            {"x": float(x), "y": float(y), "led": int(led), "amplitude": float(f"{amp:.4g}")}
            for (x, y), led, amp in zip(
                survey.points, survey.led_indices, survey.amplitudes, strict=True
            )
        ],
        "masked_leds": [],
        "mask_dead_leds": True,
    }


class SurveyRow(RequestModel):
    """One measured pilot amplitude: LED `led` received at point (`x`, `y`)."""

    x: FiniteFloat = Field(ge=0, description="m, on the receivers' plane")
    y: FiniteFloat = Field(ge=0, description="m")
    led: RequestInt = Field(ge=0, le=MAX_LED_INDEX, description="LED index (0-based, layout order)")
    amplitude: FiniteFloat = Field(description="received pilot amplitude a = h x (+ noise)")


class CalibrationCreate(RequestModel):
    """A survey to fit, and/or LEDs to mask.

    - With `survey`: fit each LED's pilot amplitude and Lambertian order, and the receiver
      gain, by least squares; build the fingerprint from the calibrated model.
    - Without `survey` (only `masked_leds`): re-use the room's active calibration (or the
      nominal layout when it has none) and only change which LEDs are masked.

    Masked LEDs' rows are dropped from the fingerprint. Dead LEDs are masked too unless
    `mask_dead_leds` is false. Measurements keep using the room's M LEDs (see localize).
    """

    model_config = ConfigDict(
        json_schema_extra=lazy_examples(calibration_example, lambda: {"masked_leds": [10]})
    )

    survey: list[SurveyRow] = Field(
        default_factory=list, max_length=MAX_SURVEY_ROWS, description="measured amplitudes"
    )
    masked_leds: list[Annotated[RequestInt, Field(ge=0, le=MAX_LED_INDEX)]] = Field(
        default_factory=list, max_length=4096, description="LED indices to drop (the full mask)"
    )
    mask_dead_leds: bool = Field(
        default=True, strict=True, description="also mask LEDs the fit finds dead"
    )
    dimmed_below: FiniteFloat = Field(
        default=0.75,
        ge=0,
        le=1,
        description="relative amplitude below which an LED is dimmed (0.75: a quarter of its "
        "light is gone; LEDs this far below the others also stay out of the receiver gain)",
    )
    dead_below: FiniteFloat = Field(
        default=0.1, ge=0, le=1, description="relative amplitude below which an LED is dead"
    )


class LedCalibration(ResponseModel):
    """The fit of one LED (nominal values for dead and unsurveyed LEDs)."""

    index: int
    flag: LedFlag = Field(description="`ok`, `dimmed`, `dead` or `unsurveyed` (no row in view)")
    masked: bool = Field(description="its rows are dropped from the fingerprint")
    pilot_amplitude: float = Field(description="fitted x_i")
    nominal_pilot_amplitude: float
    relative_amplitude: float = Field(description="x_i / nominal x_i (1: as specified)")
    lambertian_order: float = Field(description="fitted m_i")
    nominal_lambertian_order: float
    half_power_angle_deg: float
    residual_rms_before: float | None = Field(description="RMS(measured - nominal model)")
    residual_rms_after: float | None = Field(description="RMS(measured - calibrated model)")
    survey_points: int
    points_in_view: int


class Calibration(ResponseModel):
    """A calibration and, once its job succeeded, its report."""

    id: str
    room_id: str
    layout_version: int = Field(description="the layout it applies to")
    status: Literal["queued", "running", "succeeded", "failed"]
    error: str | None
    job_id: str
    created_at: datetime
    finished_at: datetime | None
    active: bool = Field(description="builds of the room's current layout use it")
    based_on: str | None = Field(description="the calibration a mask-only request re-used")
    survey_rows: int = Field(description="rows sent in the request")
    requested_masked_leds: list[int]
    mask_dead_leds: bool
    fingerprint_version: int | None = Field(description="the version built from it")
    masked_leds: list[int] | None = Field(description="the final mask (requested + dead)")
    receiver_gain: float | None = Field(description="survey receiver gain vs. nominal")
    noise_std: float | None = Field(description="estimated amplitude noise std")
    converged: bool | None
    leds: list[LedCalibration] | None


class CalibrationsList(ResponseModel):
    """A room's calibrations, newest first."""

    items: list[Calibration]
