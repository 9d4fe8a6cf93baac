"""Room layouts (request bodies) and rooms (answers)."""

from __future__ import annotations

import itertools
import math
from datetime import datetime
from typing import Any

from pydantic import ConfigDict, Field, StrictBool, field_validator, model_validator

from app.vlp.constants import (
    DEFAULT_FILTER_GAIN,
    DEFAULT_FOV_DEG,
    DEFAULT_HALF_POWER_ANGLE_DEG,
    DEFAULT_LED_NORMAL,
    DEFAULT_PILOT_AMPLITUDE,
    DEFAULT_RECEIVER_AREA_M2,
    DEFAULT_REFRACTIVE_INDEX,
    MAX_BEAM_ANGLES,
    MAX_RECEIVER_TILT_SD_DEG,
)

from .common import FiniteFloat, RequestModel, ResponseModel
from .statuses import FingerprintStatus

__all__ = [
    "FingerprintState",
    "GridSpec",
    "LedSpec",
    "ReceiverSpec",
    "Room",
    "RoomBox",
    "RoomLayout",
    "RoomsPage",
    "SurfaceReflectance",
    "paper_room_example",
]

# Sizes above this (metres) are certainly typos; the grid-point limit applies anyway.
_MAX_EXTENT_M = 10_000.0
# Physical ranges wide enough for any real fixture, narrow enough that the channel model
# stays finite: below 0.1 degrees a field of view or beam has a sine or cosine that rounds
# to 0 or 1 (infinite gains or Lambertian orders); areas, gains and amplitudes are kept
# within 18 decades of each other so that (h x)^2 neither overflows nor underflows.
_MIN_ANGLE_DEG = 0.1
_MIN_AREA_M2 = 1e-12
_MIN_FILTER_GAIN, _MAX_FILTER_GAIN = 1e-6, 100.0
# A room (or an LED height) under a centimetre is a typo; a fine grid meets the point limit.
_MIN_EXTENT_M = 0.01
_MIN_AMPLITUDE, _MAX_AMPLITUDE = 1e-9, 1e9


def paper_room_example() -> dict[str, Any]:
    """The paper's 4 x 4 x 3 m room with its 16 LEDs, as a RoomLayout body."""
    return {
        "name": "Paper room",
        "room": {"length": 4.0, "width": 4.0, "height": 3.0},
        "grid": {"step": 0.2, "receiver_height": 0.85},
        "receiver": {"area": 1e-4, "fov_deg": 70.0, "filter_gain": 1.0, "refractive_index": 1.5},
        "leds": [
            {
                "x": 0.5 + ix,
                "y": 0.5 + iy,
                "z": 3.0,
                "half_power_angle_deg": 60.0,
                "pilot_amplitude": 1.0,
            }
            for ix in range(4)
            for iy in range(4)
        ],
    }


class SurfaceReflectance(RequestModel):
    """Diffuse (Lambertian) reflectance of the room's surfaces, each in [0, 1)."""

    walls: FiniteFloat = Field(ge=0.0, lt=1.0, description="the four walls", examples=[0.7])
    floor: FiniteFloat = Field(ge=0.0, lt=1.0, description="the floor", examples=[0.2])
    ceiling: FiniteFloat = Field(ge=0.0, lt=1.0, description="the ceiling", examples=[0.8])


class RoomBox(RequestModel):
    """The room box: `x` in [0, length], `y` in [0, width], `z` in [0, height], metres."""

    length: FiniteFloat = Field(ge=_MIN_EXTENT_M, le=_MAX_EXTENT_M, description="extent along x, m")
    width: FiniteFloat = Field(ge=_MIN_EXTENT_M, le=_MAX_EXTENT_M, description="extent along y, m")
    height: FiniteFloat = Field(ge=_MIN_EXTENT_M, le=_MAX_EXTENT_M, description="ceiling height, m")
    reflectance: SurfaceReflectance | None = Field(
        default=None,
        description="the surfaces' diffuse reflectance; when given, fingerprints include the "
        "first diffuse bounce and H is the total gain (absent: line of sight only)",
    )


class GridSpec(RequestModel):
    """The candidate grid: square cells of `step` metres on the plane `z = receiver_height`.

    `length / step` and `width / step` must be whole numbers (within 1e-9 relative).
    """

    step: FiniteFloat = Field(gt=0, le=_MAX_EXTENT_M, description="cell size, m")
    receiver_height: FiniteFloat = Field(
        ge=0, le=_MAX_EXTENT_M, description="height of the photodetectors, m"
    )
    receiver_height_sd: FiniteFloat = Field(
        default=0.0,
        ge=0.0,
        le=_MAX_EXTENT_M,
        description="spread (standard deviation) of the terminals' heights around "
        "receiver_height, m; the default solver then fits each target's height",
    )
    receiver_tilt_sd: FiniteFloat = Field(
        default=0.0,
        ge=0.0,
        le=MAX_RECEIVER_TILT_SD_DEG,
        description="spread (standard deviation) of each of the two tilt components of the "
        "terminals' photodiodes, degrees (e.g. hand-held phones); the default solver then "
        "fits the tilt of each terminal that sends its own amplitudes but no normal, with "
        "this spread as its prior, and the other answers' accuracy_m holds what such tilts "
        "move an estimate by. 0: no spread declared (see receivers_level)",
    )
    # Strict: the schema says boolean, so 0 or "no" is a 422, not a guess.
    receivers_level: StrictBool = Field(
        default=False,
        description="the photodiodes face straight up (tags mounted level on carts, shelves "
        "or robots): no tilt is fitted and accuracy_m allows for none. false (hand-held "
        "phones, or not known): terminals are fitted level unless their data ask for a "
        "tilt, a room whose aggregated measurement shows it differs from its model gets "
        "each target's tilt fitted, and accuracy_m also allows for the tilts the residuals "
        "may hide. Not with receiver_tilt_sd > 0",
    )


class ReceiverSpec(RequestModel):
    """The upward-facing photodetector of every terminal."""

    area: FiniteFloat = Field(
        default=DEFAULT_RECEIVER_AREA_M2, ge=_MIN_AREA_M2, le=1.0, description="detector area, m^2"
    )
    fov_deg: FiniteFloat = Field(
        default=DEFAULT_FOV_DEG,
        ge=_MIN_ANGLE_DEG,
        le=90,
        description="field of view (half angle), degrees",
    )
    filter_gain: FiniteFloat = Field(
        default=DEFAULT_FILTER_GAIN,
        ge=_MIN_FILTER_GAIN,
        le=_MAX_FILTER_GAIN,
        description="optical filter gain",
    )
    refractive_index: FiniteFloat = Field(
        default=DEFAULT_REFRACTIVE_INDEX, ge=1, le=10, description="concentrator refractive index n"
    )


class BeamSpec(RequestModel):
    """An LED's emission pattern as a photometric table: relative intensity by the angle off
    its axis. Any scale (candela or relative); the service normalises it so that the LED
    emits its pilot amplitude. Between angles the intensity is interpolated smoothly and
    monotonically; beyond the last angle it is 0."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "angles_deg": [0, 15, 30, 45, 60, 75, 90],
                    "relative_intensity": [1.0, 1.04, 1.1, 1.08, 0.75, 0.3, 0.0],
                }
            ]
        }
    )

    angles_deg: list[FiniteFloat] = Field(
        min_length=2,
        max_length=MAX_BEAM_ANGLES,
        description="degrees off the LED's axis, from 0, increasing, at most 90",
    )
    relative_intensity: list[FiniteFloat] = Field(
        min_length=2,
        max_length=MAX_BEAM_ANGLES,
        description="intensity at each angle, >= 0 and positive at 0 degrees",
    )

    @field_validator("angles_deg")
    @classmethod
    def _angles(cls, value: list[float]) -> list[float]:
        if value[0] != 0:
            raise ValueError("angles_deg must start at 0 (the LED's axis)")
        if any(b <= a for a, b in itertools.pairwise(value)):
            raise ValueError("angles_deg must increase")
        if value[-1] > 90:
            raise ValueError("angles_deg must be at most 90")
        return value

    @field_validator("relative_intensity")
    @classmethod
    def _intensities(cls, value: list[float]) -> list[float]:
        if any(v < 0 for v in value) or value[0] <= 0:
            raise ValueError("relative_intensity must be >= 0, and positive at 0 degrees")
        return value

    @model_validator(mode="after")
    def _same_length(self) -> BeamSpec:
        if len(self.angles_deg) != len(self.relative_intensity):
            raise ValueError(
                f"relative_intensity needs one value per angle: {len(self.angles_deg)} angles, "
                f"{len(self.relative_intensity)} values"
            )
        return self


class LedSpec(RequestModel):
    """A ceiling LED: where it is, its beam, its pilot and which way its emitting face looks."""

    x: FiniteFloat = Field(ge=0, le=_MAX_EXTENT_M, description="m, in [0, room.length]")
    y: FiniteFloat = Field(ge=0, le=_MAX_EXTENT_M, description="m, in [0, room.width]")
    z: FiniteFloat | None = Field(
        default=None,
        ge=_MIN_EXTENT_M,
        le=_MAX_EXTENT_M,
        description="m, above the receivers; default room.height",
    )
    half_power_angle_deg: FiniteFloat = Field(
        default=DEFAULT_HALF_POWER_ANGLE_DEG,
        ge=_MIN_ANGLE_DEG,
        lt=90,
        description="semi-angle at half power, degrees",
    )
    pilot_amplitude: FiniteFloat = Field(
        default=DEFAULT_PILOT_AMPLITUDE,
        ge=_MIN_AMPLITUDE,
        le=_MAX_AMPLITUDE,
        description="pilot amplitude x_i",
    )
    normal: list[FiniteFloat] = Field(
        default_factory=lambda: list(DEFAULT_LED_NORMAL),
        min_length=3,
        max_length=3,
        description="unit normal [nx, ny, nz] of the emitting face in room coordinates, "
        "nz < 0 (stored normalised); default [0, 0, -1], straight down. The channel takes "
        "cos(alpha) = n . (r - s) / d for the angle of emission towards a receiver at r",
    )

    beam: BeamSpec | None = Field(
        default=None,
        description="the LED's emission pattern as a photometric table (intensity by angle "
        "off its axis); default none: a Lambertian beam of half_power_angle_deg. A survey "
        "calibration can measure it",
    )

    @field_validator("normal")
    @classmethod
    def _facing_down(cls, value: list[float]) -> list[float]:
        length = math.sqrt(sum(v * v for v in value))
        if not length > 0 or not math.isfinite(length):
            raise ValueError("normal must be a non-zero vector [nx, ny, nz]")
        if value[2] >= 0:
            raise ValueError("normal must point down (nz < 0): LEDs light the room below them")
        if value == list(DEFAULT_LED_NORMAL):
            return value
        return [v / length for v in value]


class RoomLayout(RequestModel):
    """A room: its box, candidate grid, receiver and ceiling LEDs (body of POST/PUT rooms)."""

    model_config = ConfigDict(json_schema_extra={"examples": [paper_room_example()]})

    name: str = Field(min_length=1, max_length=200, description="a human name")
    room: RoomBox
    grid: GridSpec
    receiver: ReceiverSpec = Field(default_factory=ReceiverSpec)
    leds: list[LedSpec] = Field(min_length=1, description="at least one LED")


class FingerprintState(ResponseModel):
    """Where the room's fingerprint stands."""

    status: FingerprintStatus = Field(description="state of the latest build")
    version: int | None = Field(description="the version localization uses now")
    job_id: str | None = Field(description="the latest build job")


class Room(ResponseModel):
    """A room as stored."""

    id: str
    name: str
    layout: RoomLayout = Field(description="the full layout, defaults applied")
    layout_version: int = Field(ge=1, description="1 on create, +1 on each replace")
    created_at: datetime
    updated_at: datetime
    fingerprint: FingerprintState


class RoomsPage(ResponseModel):
    """One page of rooms, oldest first."""

    items: list[Room]
    next_cursor: str | None = Field(
        description="pass as `cursor` for the next page; null at the end"
    )
