"""Seeding: the paper's room in an empty registry (``VLP_DEMO``)."""

from __future__ import annotations

from app.vlp.presets import paper_layout

from .records import RoomRecord
from .registry import Registry

__all__ = ["seed_demo_room"]


def seed_demo_room(registry: Registry) -> RoomRecord | None:
    """Create the paper's room (and queue its build) when the registry has no rooms.

    Returns the new room, or None when rooms already existed.
    """
    if registry.count_rooms():
        return None
    layout = paper_layout().to_mapping()
    return registry.create_room(name=str(layout["name"]), layout=layout)
