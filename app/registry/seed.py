"""Seeding: the paper's room in an empty registry (``VLP_DEMO``)."""

from __future__ import annotations

from app.vlp.presets import paper_layout

from .records import RoomRecord
from .registry import Registry

__all__ = ["find_demo_room", "seed_demo_room"]


def seed_demo_room(registry: Registry) -> RoomRecord | None:
    """Create the paper's room (and queue its build) when the registry has no rooms.

    Returns the new room, or None when rooms already existed.
    """
    if registry.count_rooms():
        return None
    layout = paper_layout().to_mapping()
    return registry.create_room(name=str(layout["name"]), layout=layout)


def find_demo_room(registry: Registry) -> RoomRecord | None:
    """The oldest room named like the paper's room among the first 100, or None."""
    name = paper_layout().name
    records, _ = registry.list_rooms(limit=100, cursor=None)
    return next((record for record in records if record.name == name), None)
