"""Between stored track records and the science core's arrays, and the public track."""

from __future__ import annotations

import dataclasses
import math
from datetime import UTC, datetime
from typing import Any

import numpy as np

from app.registry.records import TrackRecord
from app.schemas import RawFix, Track, TrackedState, TrackingSettings
from app.vlp.tracking import STATUS_NAMES, Rivals, TrackBank, TrackerSettings, Tracks

__all__ = [
    "filter_json",
    "public_settings",
    "rival_json",
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


def rival_json(tracks: Tracks, row: int, ids: list[str]) -> dict[str, Any]:
    """One track's other way after an ambiguous solve (:class:`~app.vlp.tracking.Rivals`) as
    stored: the other track of its pair by id, the score, the solves and the state; empty
    where the track is in no pair."""
    rivals = tracks.rivals
    if rivals is None or rivals.pair[row] == 0:
        return {}
    partner = next(
        other for other in np.nonzero(rivals.pair == rivals.pair[row])[0] if other != row
    )
    return {
        "rival": {
            "with": ids[int(partner)],
            "score": float(rivals.score[row]),
            "solves": int(rivals.solves[row]),
            "time": float(rivals.bank.times_s[row]),
            "state": filter_json(rivals.bank, row),
        }
    }


def _bank(states: list[dict[str, Any]], times_s: list[float]) -> TrackBank:
    return TrackBank(
        means=np.array([f["means"] for f in states], dtype=np.float64).reshape(-1, 2, 4),
        covariances=np.array([f["covariances"] for f in states], dtype=np.float64).reshape(
            -1, 2, 4, 4
        ),
        model_probabilities=np.array(
            [f["model_probabilities"] for f in states], dtype=np.float64
        ).reshape(-1, 2),
        times_s=np.array(times_s, dtype=np.float64),
        wild=np.array([int(f["wild"]) for f in states], dtype=np.intp),
        # Stored before the level was learned: the next fix starts it.
        noise_var=np.array([float(f.get("noise_var", math.nan)) for f in states]),
        stated_var=np.array([float(f.get("stated_var", math.nan)) for f in states]),
        # Stored before starts were told by a run: no offset to continue.
        offset=np.array([f.get("offset", [0.0, 0.0]) for f in states], dtype=np.float64).reshape(
            -1, 2
        ),
    )


def tracks_of(records: list[TrackRecord]) -> Tracks:
    """The science core's batch of the stored tracks, in the records' order."""
    if not records:
        return Tracks.empty()
    bank = _bank([r.filter for r in records], [seconds(r.state_time) for r in records])
    return Tracks(
        bank=bank,
        status=np.array([STATUS_NAMES.index(r.status) for r in records], dtype=np.intp),
        updates=np.array([r.updates for r in records], dtype=np.intp),
        misses=np.array([r.misses for r in records], dtype=np.intp),
        rivals=_rivals_of(records, bank),
    )


def _rivals_of(records: list[TrackRecord], bank: TrackBank) -> Rivals | None:
    """The stored pairs (each track names the other; a pair one of whose tracks has gone
    ends)."""
    row_of = {r.id: row for row, r in enumerate(records)}
    pair = np.zeros(len(records), dtype=np.intp)
    for row, record in enumerate(records):
        rival = record.filter.get("rival")
        partner = None if rival is None else row_of.get(rival["with"])
        if partner is None or pair[row]:
            continue
        other = records[partner].filter.get("rival")
        if other is not None and other["with"] == record.id:
            pair[[row, partner]] = int(pair.max()) + 1
    if not np.any(pair):
        return None
    paired = [records[row].filter["rival"] if pair[row] else None for row in range(len(records))]
    rival_bank = bank.put(
        np.nonzero(pair)[0],
        _bank([p["state"] for p in paired if p], [p["time"] for p in paired if p]),
    )
    return Rivals(
        pair=pair,
        bank=rival_bank,
        score=np.array([p["score"] if p else 0.0 for p in paired], dtype=np.float64),
        solves=np.array([p["solves"] if p else 0 for p in paired], dtype=np.intp),
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
