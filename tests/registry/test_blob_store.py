"""Matrices in the registry database: hosts that share only the database see the same files.

Two :class:`Registry` objects on one database with separate data directories stand for two
hosts. Corruption handling is as for local files (sha256 verified before serving, a corrupt
matrix is refused and rebuilt), and files move in chunks, never whole in memory.
"""

from __future__ import annotations

import os
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select, update

from app.registry import Registry
from app.registry._schema import matrix_blob_chunks, matrix_blobs
from app.registry.blob_store import CHUNK_BYTES, DatabaseMatrixStore
from app.registry.errors import CorruptMatrix
from app.services.matrices import rebuilding_if_corrupt
from app.settings import Settings
from tests.db_fixtures import build_now, raw_engine, small_layout


@pytest.fixture
def hosts(database_url: str, tmp_path: Path) -> Iterator[tuple[Registry, Registry]]:
    """Two migrated registries on one database, each with its own data directory."""
    pair = tuple(
        Registry(database_url=database_url, data_dir=tmp_path / name, matrix_store="database")
        for name in ("host-a", "host-b")
    )
    pair[0].migrate()
    try:
        yield pair[0], pair[1]
    finally:
        for host in pair:
            host.dispose()


def blob_count(registry: Registry) -> tuple[int, int]:
    """How many files and chunks the database holds."""
    with raw_engine(registry).connect() as conn:
        files = conn.execute(select(func.count()).select_from(matrix_blobs)).scalar_one()
        chunks = conn.execute(select(func.count()).select_from(matrix_blob_chunks)).scalar_one()
    return int(files), int(chunks)


def test_a_host_without_the_files_serves_what_another_built(
    hosts: tuple[Registry, Registry],
) -> None:
    builder, other = hosts
    room = builder.create_room(name="a", layout=small_layout(3))
    build_now(builder, room_id=room.id)
    built = builder.matrix_path(room_id=room.id, version=1, name="H")
    assert not any((other.data_dir / "matrices").rglob("*.np*"))  # nothing shared on disk
    fetched = other.matrix_path(room_id=room.id, version=1, name="H")
    assert fetched.is_relative_to(other.data_dir)
    assert fetched.read_bytes() == built.read_bytes()
    mine = builder.load_fingerprint(room_id=room.id, version=1)
    theirs = other.load_fingerprint(room_id=room.id, version=1)
    assert (mine.gains != theirs.gains).nnz == 0
    record = builder.get_fingerprint(room_id=room.id, version=1)
    assert blob_count(builder)[0] == len({info.sha256 for info in record.matrices.values()})


def test_a_corrupt_local_copy_is_fetched_again_without_a_rebuild(
    hosts: tuple[Registry, Registry],
) -> None:
    builder, other = hosts
    room = builder.create_room(name="a", layout=small_layout())
    build_now(builder, room_id=room.id)
    path = other.matrix_path(room_id=room.id, version=1, name="H")
    good = path.read_bytes()
    os.chmod(path, 0o644)
    path.write_bytes(good[:-1] + bytes([good[-1] ^ 0xFF]))
    assert other.matrix_path(room_id=room.id, version=1, name="H").read_bytes() == good
    assert other.get_room(room_id=room.id).fingerprint_status == "ready"  # nothing queued


def test_a_corrupt_database_copy_is_refused_and_the_rebuild_repairs_it(
    hosts: tuple[Registry, Registry],
) -> None:
    builder, other = hosts
    room = builder.create_room(name="a", layout=small_layout())
    build_now(builder, room_id=room.id)
    good = builder.matrix_path(room_id=room.id, version=1, name="H").read_bytes()
    with raw_engine(builder).begin() as conn:  # H's only chunk: its first byte changed
        conn.execute(update(matrix_blob_chunks).values(data=b"\x00" + good[1:]))
    with (
        pytest.raises(CorruptMatrix, match="rebuild"),
        rebuilding_if_corrupt(other, room_id=room.id),
    ):
        other.matrix_path(room_id=room.id, version=1, name="H")
    assert not (other.data_dir / "matrices").exists() or not any(
        (other.data_dir / "matrices").rglob("*.np*")
    )  # the bad bytes never became a served file
    assert other.get_room(room_id=room.id).fingerprint_status == "pending"
    assert build_now(other, room_id=room.id) == 2
    assert other.matrix_path(room_id=room.id, version=1, name="H").read_bytes() == good


def test_deleting_a_room_deletes_its_files_from_the_database(
    hosts: tuple[Registry, Registry],
) -> None:
    builder, _ = hosts
    room = builder.create_room(name="a", layout=small_layout())
    build_now(builder, room_id=room.id)
    assert blob_count(builder)[0] > 0
    builder.delete_room(room_id=room.id)
    assert blob_count(builder) == (0, 0)


def test_a_large_file_moves_in_chunks_in_bounded_memory(
    hosts: tuple[Registry, Registry], tmp_path: Path
) -> None:
    builder, _ = hosts
    writer = DatabaseMatrixStore(raw_engine(builder), tmp_path / "writer-cache")
    reader = DatabaseMatrixStore(raw_engine(builder), tmp_path / "reader-cache")
    matrix = np.random.default_rng(5).random((8, CHUNK_BYTES // 8 + 1))  # 8 chunks and a bit
    info, size_bytes = writer.cache.put(matrix)  # the local file, as a build writes it
    del matrix
    assert size_bytes > 8 * CHUNK_BYTES

    tracemalloc.start()
    try:
        writer.upload_cached(info.sha256, info.format, size_bytes)
        upload_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        fetched = reader.verified_path(info.sha256, info.format)
        fetch_peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert blob_count(builder) == (1, 9)
    assert fetched is not None
    assert fetched.read_bytes() == writer.cache.path_for(info.sha256, info.format).read_bytes()
    # A few chunks (the chunk, the driver's encoded copy) but never the whole file.
    assert upload_peak < 4 * CHUNK_BYTES, upload_peak
    assert fetch_peak < 4 * CHUNK_BYTES, fetch_peak


@pytest.mark.parametrize(
    ("registry_url", "chosen", "expected"),
    [
        (None, "auto", "files"),
        ("postgresql+psycopg://db/vlp", "auto", "database"),
        ("postgresql+psycopg://db/vlp", "files", "files"),
        (None, "database", "database"),
    ],
)
def test_the_setting_picks_the_store(
    registry_url: str | None, chosen: str, expected: str, tmp_path: Path
) -> None:
    settings = Settings.model_validate(
        {"data_dir": tmp_path, "database_url": registry_url, "matrix_store": chosen}
    )
    assert settings.resolved_matrix_store() == expected
