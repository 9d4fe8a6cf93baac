"""Between stored track records and the science core's arrays, and the public track."""

from __future__ import annotations

import dataclasses
import math
from datetime import UTC, datetime
from typing import Any

import numpy as np

from app.registry.records import TrackRecord
from app.schemas import RawFix, Track, TrackedState, TrackingSettings
from app.vlp.tracking import STATUS_NAMES, TrackBank, TrackerSettings, Tracks

__all__ = [
    "filter_json",
    "public_settings",
    "seconds",
    "to_time",
    "track_public",
    "tracked_state",
    "tracker_settings",
    "tracks_of",
]


def seconds(when: datetime) -> float:
    """POSIX seconds of an aware datetime (the science core's time axis)."""
    return when.timestamp()


def to_time(value: float) -> datetime:
    """The aware UTC datetime of POSIX seconds."""
    return datetime.fromtimestamp(value, tz=UTC)


def tracker_settings(stored: dict[str, Any] | None) -> TrackerSettings:
    """The room's settings in force: the defaults with the stored ones over them."""
    if not stored:
        return TrackerSettings()
    known = {field.name for field in dataclasses.fields(TrackerSettings)}
    return TrackerSettings(**{k: v for k, v in stored.items() if k in known and v is not None})


def public_settings(settings: TrackerSettings) -> TrackingSettings:
    """The public form of a room's tracking settings."""
    return TrackingSettings(
        **{
            name: getattr(settings, name)
            for name in TrackingSettings.model_fields
            if hasattr(settings, name)
        }
    )


def filter_json(bank: TrackBank, row: int) -> dict[str, Any]:
    """One track's filter state as stored (lists of floats)."""
    return {
        "means": bank.means[row].tolist(),
        "covariances": bank.covariances[row].tolist(),
        "model_probabilities": bank.model_probabilities[row].tolist(),
        "wild": int(bank.wild[row]),
        "noise_var": float(bank.noise_var[row]),
        "stated_var": float(bank.stated_var[row]),
        "offset": bank.offset[row].tolist(),
    }


def tracks_of(records: list[TrackRecord]) -> Tracks:
    """The science core's batch of the stored tracks, in the records' order."""
    if not records:
        return Tracks.empty()
    bank = TrackBank(
        means=np.array([r.filter["means"] for r in records], dtype=np.float64),
        covariances=np.array([r.filter["covariances"] for r in records], dtype=np.float64),
        model_probabilities=np.array(
            [r.filter["model_probabilities"] for r in records], dtype=np.float64
        ),
        times_s=np.array([seconds(r.state_time) for r in records]),
        wild=np.array([int(r.filter["wild"]) for r in records], dtype=np.intp),
        # Stored before the level was learned: the next fix starts it.
        noise_var=np.array([float(r.filter.get("noise_var", math.nan)) for r in records]),
        stated_var=np.array([float(r.filter.get("stated_var", math.nan)) for r in records]),
        # Stored before starts were told by a run: no offset to continue.
        offset=np.array(
            [r.filter.get("offset", [0.0, 0.0]) for r in records], dtype=np.float64
        ).reshape(-1, 2),
    )
    return Tracks(
        bank=bank,
        status=np.array([STATUS_NAMES.index(r.status) for r in records], dtype=np.intp),
        updates=np.array([r.updates for r in records], dtype=np.intp),
        misses=np.array([r.misses for r in records], dtype=np.intp),
    )


def tracked_state(record: TrackRecord) -> TrackedState:
    """A track's state as an estimate's ``tracked``."""
    return TrackedState(
        x=record.x,
        y=record.y,
        vx=record.vx,
        vy=record.vy,
        covariance=record.covariance,
        accuracy_m=record.accuracy_m,
        time=record.state_time,
    )


def track_public(record: TrackRecord) -> Track:
    """The public form of a stored track."""
    raw = record.last_raw
    return Track(
        id=record.id,
        terminal_id=record.terminal_id,
        status=record.status,
        x=record.x,
        y=record.y,
        vx=record.vx,
        vy=record.vy,
        covariance=record.covariance,
        accuracy_m=record.accuracy_m,
        time=record.state_time,
        updated_at=record.updated_at,
        created_at=record.created_at,
        updates=record.updates,
        raw=None if raw is None else RawFix(**raw),
    )
