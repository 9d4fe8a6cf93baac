"""Tracks of moving terminals: the track, its history points, stream events, settings."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import ConfigDict, Field

from .common import FiniteFloat, RequestInt, RequestModel, ResponseModel

__all__ = [
    "TRACK_STATUSES",
    "AccuracyMap",
    "RawFix",
    "Track",
    "TrackPoint",
    "TrackPointsPage",
    "TrackRemoved",
    "TrackStatus",
    "TrackedState",
    "TrackingSettings",
    "TrackingSettingsUpdate",
    "TracksPage",
]

TrackStatus = Literal["tentative", "confirmed", "lost"]
TRACK_STATUSES: tuple[TrackStatus, ...] = ("tentative", "confirmed", "lost")


class TrackedState(ResponseModel):
    """A track's filtered state after an estimate updated it."""

    x: float = Field(description="m")
    y: float = Field(description="m")
    vx: float = Field(description="m/s")
    vy: float = Field(description="m/s")
    covariance: list[list[float]] = Field(
        description="[[sxx, sxy], [sxy, syy]] of the position, m^2"
    )
    accuracy_m: float = Field(description="radius of the 95 % circle around (x, y), metres")
    time: datetime = Field(description="when the state holds (the measurement's time)")


class RawFix(ResponseModel):
    """One estimate as the solver gave it (before tracking)."""

    x: float = Field(description="m")
    y: float = Field(description="m")
    accuracy_m: float = Field(description="its 95 % radius, metres")


class Track(ResponseModel):
    """One moving terminal as the room tracks it."""

    id: str = Field(description="stable; never reused")
    terminal_id: str | None = Field(
        description="the terminal whose estimates update it; null for an anonymous track "
        "(estimates of aggregated measurements, associated by the service)"
    )
    status: TrackStatus = Field(
        description="`tentative` (too few updates yet), `confirmed`, `lost` (no update for "
        "the room's `lost_after_s`; removed after `drop_after_s`)"
    )
    x: float = Field(description="m")
    y: float = Field(description="m")
    vx: float = Field(description="m/s")
    vy: float = Field(description="m/s")
    covariance: list[list[float]] = Field(
        description="[[sxx, sxy], [sxy, syy]] of the position, m^2"
    )
    accuracy_m: float = Field(description="radius of the 95 % circle around (x, y), metres")
    time: datetime = Field(description="when the state holds (the last update's measurement)")
    updated_at: datetime = Field(description="when the service last changed the track")
    created_at: datetime
    updates: int = Field(description="estimates that moved it")
    raw: RawFix | None = Field(default=None, description="the estimate that last moved it")


class TracksPage(ResponseModel):
    """A page of tracks, oldest first."""

    items: list[Track]
    next_cursor: str | None


class TrackPoint(ResponseModel):
    """The track's state after one estimate, and that estimate."""

    time: datetime
    x: float = Field(description="m")
    y: float = Field(description="m")
    accuracy_m: float = Field(description="metres")
    raw: RawFix | None = Field(description="the estimate (null when none moved the track)")


class TrackPointsPage(ResponseModel):
    """A page of a track's history, oldest first."""

    items: list[TrackPoint]
    next_cursor: str | None


class TrackRemoved(ResponseModel):
    """The data of a `removed` event: the track ended (lost too long, or deleted)."""

    id: str


class TrackingSettings(ResponseModel):
    """A room's tracking settings in force (defaults for people walking indoors)."""

    max_speed_mps: float = Field(description="fastest a terminal moves, m/s")
    walking_accel_sd_mps2: float = Field(
        description="spread of a walking terminal's acceleration, m/s^2"
    )
    start_speed_sd_mps: float = Field(
        description="spread of the speed a standing terminal sets off with, m/s"
    )
    mean_dwell_s: float = Field(description="mean time between standing and walking, s")
    gate_probability: float = Field(
        description="an estimate beyond this probability of the prediction is wild: it moves "
        "the track as one on the gate would"
    )
    reset_after_wild: int = Field(description="wild estimates in a row that restart a track")
    confirm_after_updates: int = Field(description="updates that confirm a tentative track")
    tentative_max_misses: int = Field(
        description="solves in a row without it after which a tentative anonymous track ends"
    )
    lost_after_misses: int = Field(
        description="solves in a row without it after which an anonymous track is `lost`"
    )
    lost_after_s: float = Field(description="no update for this long: the track is `lost`")
    drop_after_s: float = Field(description="no update for this long: the track ends")
    history_s: float = Field(description="how long points and stream events are kept, s")


class TrackingSettingsUpdate(RequestModel):
    """Change a room's tracking settings: the fields sent replace those in force, `null`
    restores a default. Fingerprints are not rebuilt."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"lost_after_s": 10.0, "history_s": 600.0}]}
    )

    max_speed_mps: FiniteFloat | None = Field(default=None, gt=0, le=50)
    walking_accel_sd_mps2: FiniteFloat | None = Field(default=None, gt=0, le=100)
    start_speed_sd_mps: FiniteFloat | None = Field(default=None, gt=0, le=50)
    mean_dwell_s: FiniteFloat | None = Field(default=None, gt=0, le=3600)
    gate_probability: FiniteFloat | None = Field(default=None, ge=0.5, lt=1)
    reset_after_wild: RequestInt | None = Field(default=None, ge=1, le=100)
    confirm_after_updates: RequestInt | None = Field(default=None, ge=1, le=100)
    tentative_max_misses: RequestInt | None = Field(default=None, ge=1, le=100)
    lost_after_misses: RequestInt | None = Field(default=None, ge=1, le=100)
    lost_after_s: FiniteFloat | None = Field(default=None, gt=0, le=86_400)
    drop_after_s: FiniteFloat | None = Field(default=None, gt=0, le=86_400)
    history_s: FiniteFloat | None = Field(default=None, gt=0, le=86_400)


class AccuracyMap(ResponseModel):
    """How accurately the room can place one terminal, block by block: the backdrop of the
    live view. ``accuracy_m[iy][ix]`` covers ``[x_edges[ix], x_edges[ix+1]] x
    [y_edges[iy], y_edges[iy+1]]``."""

    snr_db: float = Field(description="the signal-to-noise ratio the bound assumes, dB")
    x_edges: list[float] = Field(description="metres")
    y_edges: list[float] = Field(description="metres")
    accuracy_m: list[list[float | None]] = Field(
        description="root-mean-square position error bound (Cramer-Rao, one terminal from "
        "its own amplitudes), metres; null where the position is not determined"
    )
