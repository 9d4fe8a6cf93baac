"""Survey calibrations: the request (survey rows, mask) and the report per LED."""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field

from .common import FiniteFloat, RequestInt, RequestModel, ResponseModel, lazy_examples
from .statuses import JobStatus

# Same value as app.vlp.calibration.DEFAULT_LED_POSITION_BOUND_M (a test checks); not
# imported so that importing the schemas does not load numpy.
DEFAULT_LED_POSITION_BOUND_M = 0.3
# Same value as app.vlp.calibration.DEFAULT_LED_TILT_BOUND_DEG and MAX_LED_TILT_BOUND_DEG
# (a test checks).
DEFAULT_LED_TILT_BOUND_DEG = 15.0
MAX_LED_TILT_BOUND_DEG = 45.0
# No layout has more LEDs than this (the schema's own cap; the service's limit is lower).
MAX_LED_INDEX = 1_000_000

__all__ = [
    "MAX_SURVEY_ROWS",
    "AmplitudeErrorReport",
    "CalibratedReflectance",
    "Calibration",
    "CalibrationCreate",
    "CalibrationsList",
    "LedCalibration",
    "ReflectanceSd",
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
    amplitude: FiniteFloat | None = Field(
        description="received pilot amplitude a = h x (+ noise); null: the LED was not "
        "detected at this point (never taken as a number: the fit takes it as below the "
        "survey's detection floor, the weakest amplitude detected in the survey)"
    )


class CalibrationCreate(RequestModel):
    """A survey to fit, and/or LEDs to mask.

    - With `survey`: fit each LED's pilot amplitude, Lambertian order, `x`, `y` (within
      `led_position_bound_m`) and normal (within `led_tilt_bound_deg`), the receiver gain
      and, with `fit_reflectance`, the surfaces' reflectances, by least squares (rows with a
      null amplitude censored below the detection floor); build the fingerprint from the
      calibrated model.
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
    led_position_bound_m: FiniteFloat = Field(
        default=DEFAULT_LED_POSITION_BOUND_M,
        ge=0,
        le=1,
        description="fit each LED's x and y within this many metres of the layout's (0: keep "
        "the layout's positions); needs 8 survey points in the LED's view",
    )
    led_tilt_bound_deg: FiniteFloat = Field(
        default=DEFAULT_LED_TILT_BOUND_DEG,
        ge=0,
        le=MAX_LED_TILT_BOUND_DEG,
        description="fit each LED's normal within this many degrees of the layout's (0: keep "
        "the layout's normals); needs 12 detected survey points in the LED's view",
    )
    fit_reflectance: bool = Field(
        default=False,
        strict=True,
        description="also fit the reflectance of each surface whose reflection reaches the "
        "surveyed points (walls for receivers facing up), reported with its sd; the others "
        "keep the layout's value (0 when the layout has none)",
    )
    fit_beams: bool = Field(
        default=True,
        strict=True,
        description="also measure each LED's beam (intensity by angle off its axis) where "
        "the survey tells it from a Lambertian one (16 detected points in the LED's view, and "
        "a fit better than chance); the calibrated layout then carries it as the LED's "
        "`beam` table. LEDs whose layout gives a beam keep it",
    )
    fit_gain_map: bool = Field(
        default=True,
        strict=True,
        description="last, map what the survey shows of each LED's gain beyond its fitted "
        "model, smoothly over the floor (kept only when the survey's likelihood with the map "
        "beats it without by more than the map's two parameters; LEDs with 6 detected "
        "points); the calibrated model then follows the survey near its points and the "
        "fitted model away from them",
    )
    apply_receiver_gain: bool = Field(
        default=True,
        strict=True,
        description="fold the survey receiver's fitted gain into the fingerprint (true: "
        "terminals are like the survey receiver, or the layout's absolute scale is unknown; "
        "false: keep the layout's receiver, so a survey receiver whose gain drifted does not "
        "move the fingerprint)",
    )


class BeamTable(ResponseModel):
    """An LED's beam: relative intensity by the angle off its axis (the layout's `beam`)."""

    angles_deg: list[float]
    relative_intensity: list[float]


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
    x: float | None = Field(default=None, description="fitted x of the LED, m")
    y: float | None = Field(default=None, description="fitted y of the LED, m")
    nominal_x: float | None = Field(default=None, description="the layout's x, m")
    nominal_y: float | None = Field(default=None, description="the layout's y, m")
    shift_m: float | None = Field(
        default=None, description="distance between the fitted and the layout's (x, y), m"
    )
    normal: list[float] | None = Field(
        default=None, description="fitted unit normal [nx, ny, nz] of the LED's face"
    )
    tilt_deg: float | None = Field(
        default=None, description="angle between the fitted normal and straight down, degrees"
    )
    tilt_azimuth_deg: float | None = Field(
        default=None,
        description="direction the face turns to, degrees counter-clockwise from +x in "
        "[0, 360) (0 when not tilted)",
    )
    beam: BeamTable | None = Field(
        default=None,
        description="the LED's beam in the calibrated model when it is not Lambertian: "
        "measured by the survey (`fit_beams`) or given by the layout; null: Lambertian of "
        "`half_power_angle_deg`",
    )


class CalibratedReflectance(ResponseModel):
    """The surfaces' diffuse reflectance of the calibrated model."""

    walls: float
    floor: float
    ceiling: float


class ReflectanceSd(ResponseModel):
    """Standard deviation of each fitted reflectance (null: that surface was not fitted)."""

    walls: float | None
    floor: float | None
    ceiling: float | None


class GainMapReport(ResponseModel):
    """What the survey shows of the LEDs' gains beyond their fitted model."""

    length_scale_m: float = Field(
        description="how far from a survey point its correction reaches, m"
    )
    leds: list[int] = Field(description="room indices of the LEDs the map corrects")
    evidence: float = Field(
        description="log likelihood ratio of the survey with the map over without it (nats; "
        "a map is kept from 2)"
    )


class AmplitudeErrorReport(ResponseModel):
    """How the survey's detected amplitudes scatter around the calibrated model: an error of
    scale `sqrt(noise_sd^2 + (relative_sd * model)^2)`, Gaussian (that scale its sd) or, when
    `tail_dof` is set, Student-t with that many degrees of freedom (a survey whose few errors
    lie far beyond the rest's scale); terminals that send their own amplitudes in this room
    are weighted by it and their `accuracy_m` rests on it."""

    noise_sd: float = Field(description="the amplitude noise's scale (the terminals' units)")
    relative_sd: float = Field(description="scale of the model's error relative to the signal")
    dof: float = Field(description="degrees of freedom the two rest on")
    tail_dof: float | None = Field(
        default=None,
        description="the Student-t's degrees of freedom of the errors (null: Gaussian)",
    )


class Calibration(ResponseModel):
    """A calibration and, once its job succeeded, its report."""

    id: str
    room_id: str
    layout_version: int = Field(description="the layout it applies to")
    status: JobStatus
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
    led_position_bound_m: float = Field(
        default=0.0, description="the requested bound of the LEDs' position fit, m"
    )
    led_tilt_bound_deg: float = Field(
        default=0.0, description="the requested bound of the LEDs' normal fit, degrees"
    )
    fit_reflectance: bool = Field(default=False, description="reflectances were requested")
    fit_beams: bool = Field(default=False, description="beams were requested")
    fit_gain_map: bool = Field(default=False, description="a gain map was requested")
    gain_map: GainMapReport | None = Field(
        default=None,
        description="the gain map the calibrated model carries (null: none was requested, "
        "or the survey did not show one)",
    )
    apply_receiver_gain: bool = Field(
        default=True, description="the receiver gain was folded into the fingerprint"
    )
    reflectance: CalibratedReflectance | None = Field(
        default=None,
        description="the surfaces' reflectance of the calibrated model (fitted when "
        "`fit_reflectance`, else the layout's; null: line of sight only)",
    )
    reflectance_sd: ReflectanceSd | None = Field(
        default=None, description="sd of the fitted reflectances (null when none was fitted)"
    )
    amplitude_error: AmplitudeErrorReport | None = Field(
        default=None,
        description="how the survey's amplitudes scatter around the calibrated model (null "
        "without a survey, or when it leaves no degree of freedom for it)",
    )


class CalibrationsList(ResponseModel):
    """A room's calibrations, newest first."""

    items: list[Calibration]
