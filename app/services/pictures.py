"""Pictures of a room: its plan (``map.png``) and estimates against the truth.

The plan is drawn from the layout of a fingerprint version (the current one by default, so
a calibrated room shows its fitted beams and no masked LEDs), or from the room's layout
while no fingerprint is ready. Plans are kept in the process's :class:`PictureCache`, keyed
by room, version and options.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import app.pictures as renderers  # the renderers load matplotlib on first use
from app.errors import FingerprintNotReady
from app.pictures import HeatmapKind
from app.registry import Registry
from app.schemas import LocalizationPlot
from app.vlp.layout import Layout
from app.vlp.layout_mapping import layout_from_mapping

from .fingerprint_cache import FingerprintCache
from .picture_cache import CachedPicture, PictureCache

__all__ = ["DrawnLayout", "Picture", "Plan", "localization_picture", "room_map"]


@dataclass(frozen=True)
class DrawnLayout:
    """The layout a picture draws: a fingerprint version's, or (``fingerprint_version``
    None) the room's own while it has no ready fingerprint."""

    layout: Layout
    fingerprint_version: int | None
    layout_version: int


@dataclass(frozen=True)
class Picture:
    """A PNG and the fingerprint version whose layout it draws (None: the room's layout)."""

    png: bytes
    fingerprint_version: int | None


@dataclass(frozen=True)
class Plan:
    """A room plan from the picture cache (PNG and ``ETag``) and the version it draws."""

    picture: CachedPicture
    fingerprint_version: int | None


def _layout_to_draw(
    registry: Registry, cache: FingerprintCache, *, room_id: str, version: int | None
) -> DrawnLayout:
    room = registry.get_room(room_id=room_id)
    if version is None:
        try:
            version = cache.current_version(room_id)
        except FingerprintNotReady:
            return DrawnLayout(layout_from_mapping(room.layout), None, room.layout_version)
    else:
        registry.get_fingerprint(room_id=room_id, version=version)  # 404 when unknown
    return DrawnLayout(cache.fingerprint(room_id, version).layout, version, room.layout_version)


def room_map(
    registry: Registry,
    cache: FingerprintCache,
    pictures: PictureCache,
    *,
    room_id: str,
    fingerprint_version: int | None,
    heatmap: HeatmapKind,
    snr_db: float,
    width_px: int,
) -> Plan:
    """The room plan of ``fingerprint_version`` (default: the current one), drawn once per
    (room, version, options) and then taken from ``pictures``.

    Raises
    ------
    RoomNotFound, FingerprintNotFound
    """
    drawn = _layout_to_draw(registry, cache, room_id=room_id, version=fingerprint_version)
    source = (
        ("fingerprint", drawn.fingerprint_version)
        if drawn.fingerprint_version is not None
        else ("layout", drawn.layout_version)
    )
    key = (room_id, *source, heatmap, float(snr_db), width_px)
    picture = pictures.get(key)
    if picture is None:
        png = renderers.room_map_png(
            drawn.layout, heatmap=heatmap, snr_db=snr_db, width_px=width_px
        )
        picture = pictures.put(key, png)
    return Plan(picture, drawn.fingerprint_version)


def localization_picture(
    registry: Registry, cache: FingerprintCache, *, room_id: str, body: LocalizationPlot
) -> Picture:
    """The estimates (labelled with their terminal ids) and the truth, when sent, on the
    plan of the body's version (not cached: each body draws anew).

    Raises
    ------
    RoomNotFound, FingerprintNotFound
    """
    drawn = _layout_to_draw(registry, cache, room_id=room_id, version=body.fingerprint_version)
    estimates = np.array([[p.x, p.y] for p in body.estimates], dtype=np.float64).reshape(-1, 2)
    truth = (
        None
        if body.truth is None
        else np.array([[p.x, p.y] for p in body.truth], dtype=np.float64).reshape(-1, 2)
    )
    labels = [p.terminal_id for p in body.estimates]
    png = renderers.localization_png(
        drawn.layout,
        estimates,
        truth,
        labels=labels if any(labels) else None,
        width_px=body.width_px,
        title=body.title,
    )
    return Picture(png, drawn.fingerprint_version)
