"""Rooms, API keys and migrations, on SQLite and PostgreSQL."""

from __future__ import annotations

import copy
from datetime import UTC
from typing import Any

import pytest

from app.registry import Registry
from app.registry.errors import InvalidCursor, JobNotFound, PreconditionFailed, RoomNotFound
from app.vlp.errors import GeometryError
from app.vlp.presets import paper_layout
from tests.db_fixtures import build_now, small_layout


def test_migrate_is_idempotent_and_current(registry: Registry) -> None:
    registry.migrate()
    assert registry.migrations_current()
    registry.ping()


def test_unmigrated_database_is_not_current(database_url: str, tmp_path: Any) -> None:
    fresh = Registry(database_url=database_url, data_dir=tmp_path)
    try:
        assert not fresh.migrations_current()
    finally:
        fresh.dispose()


def test_create_get_applies_defaults_and_queues_build(registry: Registry) -> None:
    room = registry.create_room(name="Lab", layout=small_layout())
    assert len(room.id) == 32
    assert room.layout_version == 1
    assert room.etag == f'"{room.id}-1"'
    assert room.fingerprint_status == "pending"
    assert room.fingerprint_version is None
    assert room.created_at.tzinfo is UTC
    assert room.layout["name"] == "Lab"
    assert room.layout["receiver"] == {
        "area": 1e-4,
        "fov_deg": 70.0,
        "filter_gain": 1.0,
        "refractive_index": 1.5,
    }
    assert room.layout["leds"][0] == {
        "x": 0.5,
        "y": 1.0,
        "z": 3.0,
        "half_power_angle_deg": 60.0,
        "pilot_amplitude": 1.0,
    }
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.room_id, job.layout_version, job.kind) == (
        "queued",
        room.id,
        1,
        "build_fingerprint",
    )
    assert registry.get_room(room_id=room.id) == room
    assert registry.count_rooms() == 1


def test_invalid_layout_is_refused_before_storing(registry: Registry) -> None:
    bad = small_layout()
    bad["grid"]["step"] = 0.3
    with pytest.raises(GeometryError) as info:
        registry.create_room(name="Bad", layout=bad)
    assert info.value.field == "grid.step"
    assert registry.count_rooms() == 0


def test_unknown_room(registry: Registry) -> None:
    with pytest.raises(RoomNotFound, match="no room"):
        registry.get_room(room_id="0" * 32)
    with pytest.raises(RoomNotFound):
        registry.delete_room(room_id="0" * 32)
    with pytest.raises(RoomNotFound):
        registry.request_build(room_id="0" * 32)


def test_list_pagination_is_stable_and_complete(registry: Registry) -> None:
    created = [registry.create_room(name=f"r{i}", layout=small_layout()) for i in range(7)]
    expected = sorted(created, key=lambda r: (r.created_at, r.id))
    seen: list[str] = []
    cursor: str | None = None
    pages = 0
    while True:
        page, cursor = registry.list_rooms(limit=3, cursor=cursor)
        pages += 1
        seen.extend(room.id for room in page)
        if cursor is None:
            break
    assert seen == [room.id for room in expected]
    assert pages == 3
    everything, last = registry.list_rooms(limit=100, cursor=None)
    assert [room.id for room in everything] == seen
    assert last is None


def test_exact_page_has_no_next_cursor(registry: Registry) -> None:
    for i in range(2):
        registry.create_room(name=f"r{i}", layout=small_layout())
    page, cursor = registry.list_rooms(limit=2, cursor=None)
    assert len(page) == 2
    assert cursor is None


@pytest.mark.parametrize("cursor", ["not-base64!", "Zm9v", ""], ids=["junk", "no-sep", "empty"])
def test_invalid_cursor(registry: Registry, cursor: str) -> None:
    with pytest.raises(InvalidCursor) as info:
        registry.list_rooms(limit=2, cursor=cursor)
    assert info.value.field == "cursor"


def test_replace_bumps_version_and_stale_replace_fails(registry: Registry) -> None:
    room = registry.create_room(name="Lab", layout=small_layout(2))
    replaced = registry.replace_room(
        room_id=room.id, name="Lab 2", layout=small_layout(3), expected_layout_version=1
    )
    assert replaced.layout_version == 2
    assert replaced.etag == f'"{room.id}-2"'
    assert replaced.name == "Lab 2"
    assert len(replaced.layout["leds"]) == 3
    assert replaced.updated_at >= room.updated_at
    assert replaced.created_at == room.created_at
    with pytest.raises(PreconditionFailed, match="layout_version 2"):
        registry.replace_room(
            room_id=room.id, name="stale", layout=small_layout(1), expected_layout_version=1
        )
    assert registry.get_room(room_id=room.id) == replaced
    with pytest.raises(RoomNotFound):
        registry.replace_room(
            room_id="f" * 32, name="x", layout=small_layout(), expected_layout_version=1
        )


def test_failed_replace_leaves_the_old_layout(registry: Registry) -> None:
    room = registry.create_room(name="Lab", layout=small_layout(2))
    bad = copy.deepcopy(small_layout(2))
    bad["leds"][0]["x"] = 99.0
    with pytest.raises(GeometryError):
        registry.replace_room(room_id=room.id, name="Bad", layout=bad, expected_layout_version=1)
    assert registry.get_room(room_id=room.id) == room


def test_replace_repoints_the_queued_job(registry: Registry) -> None:
    room = registry.create_room(name="Lab", layout=small_layout(2))
    replaced = registry.replace_room(
        room_id=room.id, name="Lab", layout=small_layout(3), expected_layout_version=1
    )
    assert replaced.job_id == room.job_id
    job = registry.get_job(job_id=replaced.job_id or "")
    assert (job.status, job.layout_version) == ("queued", 2)


def test_delete_removes_rows_jobs_and_unshared_files(registry: Registry) -> None:
    shared = registry.create_room(name="A", layout=paper_layout().to_mapping())
    twin = registry.create_room(name="B", layout=paper_layout().to_mapping())
    other = registry.create_room(name="C", layout=small_layout(2))
    for room in (shared, twin, other):
        build_now(registry, room_id=room.id)
    paths = {
        room.id: {
            name: registry.matrix_path(room_id=room.id, version=1, name=name)
            for name in registry.get_fingerprint(room_id=room.id, version=1).matrices
        }
        for room in (shared, twin, other)
    }
    assert paths[shared.id] == paths[twin.id]  # same layout => same content => same files
    registry.delete_room(room_id=shared.id)
    registry.delete_room(room_id=other.id)
    assert all(path.exists() for path in paths[twin.id].values())
    assert not any(path.exists() for path in paths[other.id].values())
    for room in (shared, other):
        with pytest.raises(RoomNotFound):
            registry.get_room(room_id=room.id)
    with pytest.raises(JobNotFound):
        registry.get_job(job_id=other.job_id or "")
    assert registry.count_rooms() == 1
