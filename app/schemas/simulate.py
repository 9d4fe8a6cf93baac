"""Simulated measurements with their ground truth."""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field

from app.vlp.constants import MAX_TARGETS

from ._common import FiniteFloat, RequestInt, RequestModel, ResponseModel
from .localize import Measurement, ModelName, SolverName

__all__ = ["Simulation", "SimulationRequest", "TruthTarget"]

Point = tuple[FiniteFloat, FiniteFloat]


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
        default=None, ge=0, description="noise std of one amplitude (instead of snr_db)"
    )
    model: ModelName = Field(default="correlation")
    form: Literal["matrix", "upper", "terminals"] = Field(
        default="matrix",
        description="correlation as a full `matrix` or its `upper` triangle, or per-terminal "
        "amplitudes (`terminals`); the power model sends `power` unless `terminals`",
    )
    solver: SolverName = Field(default="gridless", description="copied into the measurement")
    seed: RequestInt | None = Field(
        default=None, ge=0, le=2**64 - 1, description="for a reproducible simulation"
    )


class TruthTarget(ResponseModel):
    """Where a simulated terminal really is."""

    x: float
    y: float
    grid_index: int
    terminal_id: str | None


class Simulation(ResponseModel):
    """A ready-to-send measurement and the truth behind it."""

    measurement: Measurement = Field(
        description="a body for localize, as sent: only the fields it needs (no nulls)"
    )
    truth: list[TruthTarget]
    noise_std: float = Field(description="noise std of one amplitude used")
    fingerprint_version: int
