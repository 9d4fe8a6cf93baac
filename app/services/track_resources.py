"""Reading a room's tracks and changing its tracking settings: registry records in, public
schemas out (the writes that move tracks are :mod:`app.services.tracking`'s)."""

from __future__ import annotations

from datetime import datetime

import numpy as np

from app.errors import InvalidFields, VLPError
from app.pictures.heatmaps import amplitude_crlb_m, noise_std_on_samples, sample_grid
from app.registry import Registry
from app.registry.records import TrackEventRecord
from app.schemas import (
    AccuracyMap,
    RawFix,
    Track,
    TrackingSettings,
    TrackingSettingsUpdate,
    TrackPoint,
    TrackPointsPage,
    TracksPage,
)
from app.vlp.layout_mapping import layout_from_mapping

from ._track_state import public_settings, track_public, tracker_settings

__all__ = [
    "ACCURACY_SNR_DB",
    "accuracy_map",
    "events_since",
    "get_track",
    "latest_sequence",
    "list_tracks",
    "track_points",
    "tracking_settings",
    "update_tracking_settings",
]

# The view's backdrop: the accuracy bound at this SNR (the simulator's default), on at most
# this many blocks per side.
ACCURACY_SNR_DB = 30.0
ACCURACY_SAMPLES_PER_SIDE = 48


def list_tracks(
    registry: Registry, *, room_id: str, statuses: tuple[str, ...], limit: int, cursor: str | None
) -> TracksPage:
    """A page of a room's tracks with one of ``statuses``. RoomNotFound."""
    registry.get_room(room_id=room_id)
    records, next_cursor = registry.tracks.list_tracks(
        room_id=room_id, statuses=statuses, limit=limit, cursor=cursor
    )
    return TracksPage(items=[track_public(r) for r in records], next_cursor=next_cursor)


def get_track(registry: Registry, *, room_id: str, track_id: str) -> Track:
    """One track. TrackNotFound."""
    return track_public(registry.tracks.get_track(room_id=room_id, track_id=track_id))


def track_points(
    registry: Registry,
    *,
    room_id: str,
    track_id: str,
    since: datetime | None,
    limit: int,
    cursor: str | None,
) -> TrackPointsPage:
    """A page of a track's history. TrackNotFound, InvalidCursor."""
    points, next_cursor = registry.tracks.list_points(
        room_id=room_id, track_id=track_id, since=since, limit=limit, cursor=cursor
    )
    return TrackPointsPage(
        items=[
            TrackPoint(
                time=p.time,
                x=p.x,
                y=p.y,
                accuracy_m=p.accuracy_m,
                raw=None
                if p.raw_x is None or p.raw_y is None or p.raw_accuracy_m is None
                else RawFix(x=p.raw_x, y=p.raw_y, accuracy_m=p.raw_accuracy_m),
            )
            for p in points
        ],
        next_cursor=next_cursor,
    )


def tracking_settings(registry: Registry, *, room_id: str) -> TrackingSettings:
    """The room's tracking settings in force. RoomNotFound."""
    registry.get_room(room_id=room_id)
    return public_settings(tracker_settings(registry.tracks.get_settings(room_id=room_id)))


def update_tracking_settings(
    registry: Registry, *, room_id: str, body: TrackingSettingsUpdate
) -> TrackingSettings:
    """Replace the fields sent (null: back to the default). RoomNotFound; InvalidFields
    when the result is inconsistent (e.g. ``drop_after_s`` below ``lost_after_s``)."""
    stored = dict(registry.tracks.get_settings(room_id=room_id) or {})
    for name in body.model_fields_set:
        stored[name] = getattr(body, name)
    stored = {k: v for k, v in stored.items() if v is not None}
    try:
        settings = tracker_settings(stored)
    except VLPError as exc:
        raise InvalidFields([(exc.field or "body", exc.message)]) from exc
    registry.tracks.put_settings(room_id=room_id, settings=stored or None)
    return public_settings(settings)


def events_since(
    registry: Registry, *, room_id: str, after: int, limit: int
) -> list[TrackEventRecord]:
    """The room's kept events after sequence ``after``, oldest first."""
    return registry.tracks.events_since(room_id=room_id, after=after, limit=limit)


def accuracy_map(
    registry: Registry, *, room_id: str, snr_db: float = ACCURACY_SNR_DB
) -> AccuracyMap:
    """The room's single-terminal accuracy bound on a coarse grid (the view's backdrop)."""
    layout = layout_from_mapping(registry.get_room(room_id=room_id).layout)
    grid = sample_grid(layout, ACCURACY_SAMPLES_PER_SIDE)
    noise = noise_std_on_samples(layout, grid.points, snr_db)
    bound = amplitude_crlb_m(layout, grid.points, noise).reshape(grid.shape)
    return AccuracyMap(
        snr_db=snr_db,
        x_edges=grid.x_edges.tolist(),
        y_edges=grid.y_edges.tolist(),
        accuracy_m=[[float(v) if np.isfinite(v) else None for v in row] for row in bound],
    )


def latest_sequence(registry: Registry, *, room_id: str) -> int:
    """The room's newest stream event (0: none yet)."""
    return registry.tracks.latest_sequence(room_id=room_id)
