"""Migrations under concurrency, unavailability, seeding and the public surface."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

import app.jobs
import app.registry
import app.registry.errors
from app.registry import Registry
from app.registry._schema import metadata
from app.registry.errors import RegistryError, RegistryUnavailable
from app.registry.seed import seed_demo_room
from app.vlp.presets import paper_layout
from tests.db_fixtures import raw_engine


def test_concurrent_migrations_are_safe(database_url: str, tmp_path: Path) -> None:
    registries = [Registry(database_url=database_url, data_dir=tmp_path) for _ in range(3)]
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(registries))

    def run(reg: Registry) -> None:
        barrier.wait()
        try:
            reg.migrate()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(reg,)) for reg in registries]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    try:
        assert errors == [], [repr(e.__cause__) for e in errors]
        assert all(reg.migrations_current() for reg in registries)
        assert registries[0].count_rooms() == 0
    finally:
        for reg in registries:
            reg.dispose()


def test_unreachable_database_is_unavailable(tmp_path: Path) -> None:
    reg = Registry(
        database_url="postgresql+psycopg://postgres@127.0.0.1:1/test?connect_timeout=2",
        data_dir=tmp_path,
    )
    try:
        with pytest.raises(RegistryUnavailable) as info:
            reg.ping()
        assert "SELECT" not in str(info.value)
        with pytest.raises(RegistryUnavailable):
            reg.count_rooms()
    finally:
        reg.dispose()


def test_seed_demo_room_only_into_an_empty_registry(registry: Registry) -> None:
    room = seed_demo_room(registry)
    assert room is not None
    assert room.name == "Paper room"
    assert room.layout == paper_layout().to_mapping()
    assert room.fingerprint_status == "pending"
    assert seed_demo_room(registry) is None
    assert registry.count_rooms() == 1


def test_public_surface() -> None:
    assert sorted(app.registry.__all__) == [
        "CalibrationRecord",
        "FingerprintRecord",
        "JobRecord",
        "MatrixInfo",
        "Registry",
        "RoomRecord",
    ]
    assert sorted(app.jobs.__all__) == [
        "BuildTask",
        "EmbeddedWorkers",
        "build_and_store",
        "run_worker",
    ]
    for name in app.registry.errors.__all__:
        error = getattr(app.registry.errors, name)
        assert issubclass(error, RegistryError)


def test_migrations_match_the_table_definitions(registry: Registry) -> None:
    with raw_engine(registry).connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), metadata)
    assert diff == []
