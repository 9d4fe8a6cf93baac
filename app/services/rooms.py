"""Rooms: a layout checked against the size limits and the geometry rules before it is stored.

Creating and replacing a room go through here; reading, listing and deleting are plain
registry calls made by the router.
"""

from __future__ import annotations

import math
from typing import Any

from app.errors import InvalidFields, PreconditionFailed
from app.registry import Registry, RoomRecord
from app.schemas import RoomLayout
from app.settings import Settings
from app.vlp.layout_mapping import layout_from_mapping

from .fingerprint_cache import FingerprintCache

__all__ = ["create_room", "etag_matches", "replace_room", "validated_layout"]


def validated_layout(body: RoomLayout, settings: Settings) -> dict[str, Any]:
    """The layout mapping with defaults applied, after the size limits and geometry checks.

    The grid size is computed from the numbers alone, before anything is allocated.

    Raises
    ------
    InvalidFields
        More LEDs or grid points than the settings allow.
    GeometryError
        A layout the science core refuses (naming its field).
    """
    if len(body.leds) > settings.max_leds:
        raise InvalidFields(
            [("leds", f"at most {settings.max_leds} LEDs are allowed, got {len(body.leds)}")]
        )
    step = body.grid.step
    points = (body.room.length / step) * (body.room.width / step)
    if not math.isfinite(points) or points > settings.max_grid_points * (1 + 1e-9):
        raise InvalidFields(
            [
                (
                    "grid.step",
                    f"grid.step {step!r} m gives about {points:.3g} grid points; at "
                    f"most {settings.max_grid_points} are allowed",
                )
            ]
        )
    layout = layout_from_mapping(body.model_dump())
    return layout.to_mapping()


def etag_matches(header: str, etag: str) -> bool:
    """Whether an ``If-Match`` / ``If-None-Match`` value names ``etag`` (or is ``*``)."""
    candidates = [part.strip() for part in header.split(",")]
    return "*" in candidates or etag in candidates


def create_room(registry: Registry, *, body: RoomLayout, settings: Settings) -> RoomRecord:
    """Store a new room and queue its first fingerprint build.

    Raises
    ------
    InvalidFields, GeometryError
        See :func:`validated_layout`.
    """
    return registry.create_room(name=body.name, layout=validated_layout(body, settings))


def replace_room(
    registry: Registry,
    cache: FingerprintCache,
    *,
    room_id: str,
    body: RoomLayout,
    settings: Settings,
    if_match: str,
) -> RoomRecord:
    """Replace the room's layout when ``if_match`` names its current ETag; its cached
    fingerprint is forgotten (localization re-reads the current version).

    Raises
    ------
    InvalidFields, GeometryError
        See :func:`validated_layout`.
    RoomNotFound
    PreconditionFailed
        ``if_match`` is not the room's current ETag (or the room changed meanwhile).
    """
    layout = validated_layout(body, settings)
    current = registry.get_room(room_id=room_id)
    if not etag_matches(if_match, current.etag):
        raise PreconditionFailed(
            f"If-Match {if_match} is not the room's current ETag "
            f"{current.etag}; read the room again"
        )
    record = registry.replace_room(
        room_id=room_id,
        name=body.name,
        layout=layout,
        expected_layout_version=current.layout_version,
    )
    cache.forget(room_id)
    return record
