"""Cooperation epochs: create one, post a terminal's amplitudes, read the outcome."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import ConfigDict, Field

from app.vlp.constants import MAX_TARGETS

from .common import MAX_VERSION, FiniteFloat, RequestInt, RequestModel, ResponseModel
from .localize import (
    TERMINAL_ID_PATTERN,
    DetectedAmplitudes,
    DetectionFloor,
    Localization,
    ModelName,
    SolverName,
    terminals_example,
)
from .statuses import EpochStatus

__all__ = [
    "MAX_WINDOW_S",
    "Epoch",
    "EpochCreate",
    "EpochMeasurement",
    "EpochStatus",
    "epoch_create_examples",
    "epoch_measurement_examples",
]

# The contract's four statuses. Internally an epoch may also be `solving` (closed, one
# process is solving it); it is shown as `open` with `closed: true` so clients built on
# the four-value enum keep working.
# A cooperation window is short: terminals that moved for a minute are no longer where they
# measured, so longer windows would only mix stale positions.
MAX_WINDOW_S = 60.0


def epoch_create_examples() -> dict[str, dict[str, Any]]:
    """Bodies to open an epoch from the Swagger UI: a minute leaves time to post by hand."""
    return {
        "by-hand": {
            "summary": "a 60 s window for two terminals (time to post by hand)",
            "value": {
                "model": "correlation",
                "solver": "gridless",
                "min_terminals": 2,
                "window_s": 60,
            },
        },
        "defaults": {"summary": "every default (a 2 s window)", "value": {}},
    }


def epoch_measurement_examples() -> dict[str, dict[str, Any]]:
    """Two posts for the demo (paper) room: the noiseless amplitudes at (1.0, 1.2) m and at
    (2.9, 3.1) m, under the names the Swagger UI shows in its example list."""
    terminals = terminals_example()["terminals"][:2]
    return {
        terminal["id"]: {
            "summary": f"terminal {terminal['id']} of the demo room",
            "value": {"terminal_id": terminal["id"], "amplitudes": terminal["amplitudes"]},
        }
        for terminal in terminals
    }


class EpochCreate(RequestModel):
    """A cooperation window: terminals post their own amplitudes until `window_s` has passed
    (or `solve` is called); then the service sums them and solves once.

    `targets` left out means one target per terminal that took part, so every estimate is
    labelled with its terminal. The epoch uses the room's current fingerprint version (or
    `fingerprint_version`) from creation to its end.
    """

    model_config = ConfigDict(
        json_schema_extra={"examples": [epoch_create_examples()["by-hand"]["value"]]}
    )

    model: ModelName = Field(default="correlation", description="how the posts are aggregated")
    targets: RequestInt | None = Field(
        default=None,
        ge=1,
        le=MAX_TARGETS,
        description="K; default: the number of terminals that posted",
    )
    solver: SolverName = Field(default="gridless", description="as for localize")
    min_terminals: RequestInt = Field(
        default=2,
        ge=1,
        le=MAX_TARGETS,
        description="fewer terminals than this when the window closes: the epoch expires",
    )
    window_s: FiniteFloat = Field(
        default=2.0,
        gt=0,
        le=MAX_WINDOW_S,
        description=f"seconds from creation until the window closes (at most {MAX_WINDOW_S:g})",
    )
    fingerprint_version: RequestInt | None = Field(
        default=None, ge=1, le=MAX_VERSION, description="default: the room's current version"
    )
    track: bool = Field(
        default=True,
        strict=True,
        description="the solved epoch updates the room's tracks at its close time (each "
        "estimate then carries `track_id` and `tracked`)",
    )


class EpochMeasurement(RequestModel):
    """One terminal's amplitudes (null for an LED it did not detect, as in localize's
    `terminals`); posting again with the same `terminal_id` replaces them."""

    terminal_id: str = Field(
        pattern=TERMINAL_ID_PATTERN, description="the terminal's own id", examples=["t1"]
    )
    amplitudes: DetectedAmplitudes
    detection_floor: DetectionFloor = None


class Epoch(ResponseModel):
    """A cooperation epoch and, once solved, its localization.

    `status`: `open` (the window or its solve is still under way), `solved`, `expired`
    (fewer than `min_terminals` took part) or `failed` (see `error`). `closed` tells whether
    the window has closed: an `open` epoch with `closed: true` is being solved right now and
    answers posts with 409.
    """

    id: str
    room_id: str
    status: EpochStatus
    closed: bool = Field(description="the window has closed (no more posts)")
    terminals: int = Field(description="how many terminals have posted")
    created_at: datetime
    expires_at: datetime = Field(description="when the window closes")
    model: ModelName
    solver: str
    targets: int | None = Field(description="K as requested (null: one per terminal)")
    min_terminals: int
    window_s: float
    fingerprint_version: int = Field(description="the fingerprint version the epoch uses")
    track: bool = Field(default=True, description="the solution updates the room's tracks")
    localization: Localization | None = Field(
        description="when solved; every estimate carries its `terminal_id`"
    )
    error: str | None = Field(description="why the epoch failed")
