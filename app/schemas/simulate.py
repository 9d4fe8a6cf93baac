"""Simulated measurements with their ground truth."""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field

from app.vlp.constants import MAX_TARGETS

from .common import FiniteFloat, RequestInt, RequestModel, ResponseModel
from .localize import Measurement, ModelName, SolverName
from .rooms import SurfaceReflectance

__all__ = ["ImpairmentsSpec", "Simulation", "SimulationRequest", "TruthTarget"]

Point = tuple[FiniteFloat, FiniteFloat]


class ImpairmentsSpec(RequestModel):
    """How the simulated room differs from its layout (all optional; absent = as modelled).

    Ranges seen in practice: reflectance of walls 0.5-0.8, floor 0.2, ceiling 0.8; terminal
    gains a few to 10 % apart; heights a few to 15 cm apart; hand-held tilts up to 10-20
    degrees; LED flux within about 5-7 % and beams within a few degrees
    (docs/explanation/real-rooms.md).
    """

    reflectance: SurfaceReflectance | None = Field(
        default=None, description="the room's TRUE surfaces (first diffuse bounce)"
    )
    gain_sd: FiniteFloat = Field(
        default=0.0, ge=0.0, le=1.0, description="terminals' gain spread, relative sd"
    )
    height_sd_m: FiniteFloat = Field(
        default=0.0, ge=0.0, le=2.0, description="terminals' heights around receiver_height, sd, m"
    )
    tilt_max_deg: FiniteFloat = Field(
        default=0.0, ge=0.0, le=60.0, description="photodiode tilt, uniform in [0, max], degrees"
    )
    led_amplitude_sd: FiniteFloat = Field(
        default=0.0, ge=0.0, le=1.0, description="LEDs' pilot amplitudes, relative sd"
    )
    led_half_power_sd_deg: FiniteFloat = Field(
        default=0.0, ge=0.0, le=20.0, description="LEDs' half-power angles, sd, degrees"
    )
    led_position_sd_m: FiniteFloat = Field(
        default=0.0, ge=0.0, le=1.0, description="LEDs' x, y placement, sd, m"
    )
    common_scale: FiniteFloat = Field(
        default=1.0, gt=0.0, le=1e6, description="one factor on every amplitude"
    )


class SimulationRequest(RequestModel):
    """What to simulate: random (`targets`) or given (`positions`) terminals and the noise.

    The answer's `measurement` can be sent unchanged to `POST /v1/rooms/{room_id}/localize`.
    """

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"targets": 8, "snr_db": 30, "seed": 7},
                {
                    "targets": 2,
                    "snr_db": 30,
                    "model": "correlation",
                    "form": "terminals",
                    "seed": 7,
                },
                {"positions": [[1.0, 1.2], [2.9, 3.1]], "noise_std": 0.0, "form": "upper"},
            ]
        }
    )

    targets: RequestInt | None = Field(
        default=None, ge=1, le=MAX_TARGETS, description="K random terminals (one per grid cell)"
    )
    positions: list[Point] | None = Field(
        default=None,
        min_length=1,
        max_length=MAX_TARGETS,
        description="given terminal positions [[x, y], ...], m",
    )
    snr_db: FiniteFloat | None = Field(
        default=None,
        ge=-50,
        le=200,
        description="mean(J) / noise variance of one amplitude, dB; default 30",
    )
    noise_std: FiniteFloat | None = Field(
        default=None,
        ge=0,
        le=1e40,
        description="noise std of one amplitude (instead of snr_db); at most 1e40 so that "
        "sums of squared amplitudes stay finite",
    )
    model: ModelName = Field(default="correlation")
    form: Literal["matrix", "upper", "terminals"] = Field(
        default="matrix",
        description="correlation as a full `matrix` or its `upper` triangle, or per-terminal "
        "amplitudes (`terminals`); the power model sends `power` unless `terminals`",
    )
    solver: SolverName = Field(default="gridless", description="copied into the measurement")
    impairments: ImpairmentsSpec | None = Field(
        default=None,
        description="simulate a real room instead of the layout's model (needs snr_db, not "
        "noise_std); the truth then carries each terminal's height, normal and gain",
    )
    seed: RequestInt | None = Field(
        default=None, ge=0, le=2**64 - 1, description="for a reproducible simulation"
    )


class TruthTarget(ResponseModel):
    """Where a simulated terminal really is."""

    x: float
    y: float
    grid_index: int
    terminal_id: str | None
    z: float | None = Field(default=None, description="its height, m (with impairments)")
    normal: list[float] | None = Field(
        default=None, description="its photodiode's unit normal (with impairments)"
    )
    gain: float | None = Field(default=None, description="its gain (with impairments)")


class Simulation(ResponseModel):
    """A ready-to-send measurement and the truth behind it."""

    measurement: Measurement = Field(
        description="a body for localize, as sent: only the fields it needs (no nulls)"
    )
    truth: list[TruthTarget]
    noise_std: float = Field(description="noise std of one amplitude used")
    fingerprint_version: int
