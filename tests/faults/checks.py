"""What must hold after any fault: nothing lost, nothing half-written, nothing stuck."""

from __future__ import annotations

import hashlib
from pathlib import Path

from app.registry import Registry

__all__ = ["assert_nothing_lost", "assert_store_complete", "registry_of"]


def registry_of(data_dir: Path, database_url: str | None = None) -> Registry:
    """A registry on the same database and store as the processes under test."""
    url = database_url or f"sqlite:///{(data_dir / 'registry.sqlite3').resolve()}"
    return Registry(database_url=url, data_dir=data_dir)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def assert_store_complete(registry: Registry) -> None:
    """Every visible file in the matrix store is whole, and every stored matrix has one.

    Visible: any name that does not start with ``.tmp-`` (a temporary file of an interrupted
    write, which is never served). Whole: its bytes hash to its name. Every matrix of every
    fingerprint version of every room verifies through the registry (hash checked), and no
    temporary file is referred to.
    """
    referenced: set[Path] = set()
    rooms, cursor = registry.list_rooms(limit=1000, cursor=None)
    assert cursor is None
    for room in rooms:
        for fingerprint in registry.list_fingerprints(room_id=room.id):
            for name in fingerprint.matrices:
                referenced.add(
                    registry.matrix_path(room_id=room.id, version=fingerprint.version, name=name)
                )
    root = registry.store.root
    for path in root.glob("*/*") if root.is_dir() else []:
        if path.name.startswith(".tmp-"):
            assert path not in referenced, f"temporary file {path} is referred to"
            continue
        sha256, _, fmt = path.name.partition(".")
        assert fmt in ("npy", "npz") and path.parent.name == sha256[:2], path
        assert _sha256(path) == sha256, f"{path} does not hash to its name: a partial file"
    assert all(path.is_file() for path in referenced)


def assert_nothing_lost(registry: Registry, *, rooms: dict[str, int | None]) -> None:
    """No job is left ``running``; each room in ``rooms`` exists with at least that version."""
    assert registry.count_jobs_by_status()["running"] == 0
    for room_id, version in rooms.items():
        room = registry.get_room(room_id=room_id)
        if version is not None:
            assert room.fingerprint_version is not None
            assert room.fingerprint_version >= version
    assert_store_complete(registry)
