"""Database fixtures shared by the registry, jobs and API tests (a pytest plugin).

``database_url`` is parametrized over a fresh SQLite file and a fresh schema on the real
PostgreSQL (``VLP_TEST_POSTGRES_URL``, default ``postgresql+psycopg://postgres@127.0.0.1:5432/test``).
PostgreSQL is required: when it does not answer the test fails with a clear message (the
CI entry point starts it), it is never skipped.

Registered for the whole suite by ``pytest_plugins`` in ``tests/conftest.py``: every test
can ask for these fixtures by name, no import needed. ``registry`` runs on the ``clock``
fixture, the real clock; a test module that steps time overrides ``clock`` with a
:class:`app.clock.FakeClock`.
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest
from sqlalchemy import Engine, make_url

from app.clock import Clock, SystemClock
from app.jobs.build import store_fingerprint
from app.jobs.calibrate import apply_calibration
from app.registry import Registry
from app.registry.records import ClaimedJob, StoredBuild
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Room
from app.vlp.layout_mapping import layout_from_mapping
from bench.hall_build import million_point_hall

__all__ = [
    "build_now",
    "claim_next",
    "clock",
    "database_url",
    "hall_layout",
    "million_point_hall",
    "overwrite",
    "postgres_url",
    "raw_engine",
    "record_build",
    "registry",
    "small_layout",
    "sqlite_url",
    "stored_build",
]

POSTGRES_URL = os.environ.get(
    "VLP_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
)
BACKENDS = [
    pytest.param("sqlite", id="sqlite"),
    pytest.param("postgresql", id="postgresql", marks=pytest.mark.postgres),
]


def _admin_connect() -> psycopg.Connection[tuple[object, ...]]:
    url = make_url(POSTGRES_URL)
    try:
        return psycopg.connect(
            host=url.host or "127.0.0.1",
            port=url.port or 5432,
            dbname=url.database or "test",
            user=url.username or "postgres",
            password=url.password,
            autocommit=True,
            connect_timeout=5,
        )
    except psycopg.OperationalError as exc:
        pytest.fail(
            f"PostgreSQL at {url.render_as_string(hide_password=True)} does not answer ({exc}); "
            "start it (scripts/ensure-postgres.sh) or set VLP_TEST_POSTGRES_URL",
            pytrace=False,
        )


def _fresh_schema_url() -> Iterator[str]:
    schema = f"t_{uuid.uuid4().hex[:20]}"
    with _admin_connect() as admin:
        admin.execute(f'CREATE SCHEMA "{schema}"')
    url = make_url(POSTGRES_URL).update_query_dict({"options": f"-csearch_path={schema}"})
    try:
        yield url.render_as_string(hide_password=False)
    finally:
        with _admin_connect() as admin:
            admin.execute(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE')


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    """A fresh SQLite registry file."""
    return f"sqlite:///{tmp_path / 'registry.sqlite3'}"


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A URL whose connections live in a fresh, private schema of the test PostgreSQL."""
    yield from _fresh_schema_url()


@pytest.fixture(params=BACKENDS)
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh registry database, once on SQLite and once on PostgreSQL."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'registry.sqlite3'}"
    else:
        yield from _fresh_schema_url()


@pytest.fixture
def clock() -> Clock:
    """The clock of ``registry``: the real one (override with a FakeClock to step time)."""
    return SystemClock()


@pytest.fixture
def registry(database_url: str, tmp_path: Path, clock: Clock) -> Iterator[Registry]:
    """A migrated registry on ``database_url`` with its matrix store in ``tmp_path``."""
    reg = Registry(
        database_url=database_url, data_dir=tmp_path / "data", max_build_attempts=3, clock=clock
    )
    reg.migrate()
    try:
        yield reg
    finally:
        reg.dispose()


def raw_engine(registry: Registry) -> Engine:
    """The registry's engine, for tests that read or damage stored rows directly (schema
    checks, row counts, a corrupted chunk). Test-only: the service reaches the database only
    through :class:`Registry` and its ``jobs`` and ``epochs`` doors."""
    return registry._engine


def claim_next(
    registry: Registry,
    *,
    worker_id: str = "w",
    lease_seconds: float = 30.0,
    room_id: str | None = None,
) -> ClaimedJob | None:
    """Claim the oldest claimable job as a worker would, at the registry clock's now."""
    return registry.jobs.claim(
        worker_id=worker_id,
        now=registry.clock.now(),
        lease_seconds=lease_seconds,
        max_attempts=registry.max_build_attempts,
        room_id=room_id,
    )


def record_build(registry: Registry, claimed: ClaimedJob, build: StoredBuild) -> int | None:
    """Record a finished build as a worker would (at the registry clock's now); the version."""
    return registry.jobs.complete(claimed=claimed, build=build, now=registry.clock.now())


def build_now(registry: Registry, *, room_id: str, worker_id: str = "test-builder") -> int:
    """Run the room's queued build in this process (no worker) and return the new version.

    For tests that need a ready fingerprint quickly: claims the room's job, builds with
    :func:`app.jobs.build.store_fingerprint` and records it exactly as a worker would.
    """
    claimed = claim_next(registry, worker_id=worker_id, lease_seconds=60.0, room_id=room_id)
    if claimed is None:
        raise AssertionError(f"room {room_id} has no claimable build job")
    version = record_build(registry, claimed, stored_build(registry, claimed))
    if version is None:
        raise AssertionError(f"job {claimed.job_id} was lost while building")
    return version


def stored_build(registry: Registry, claimed: ClaimedJob) -> StoredBuild:
    """Build a claimed job's layout in this process and put its matrices into the store."""
    started = time.perf_counter()
    layout = layout_from_mapping(claimed.layout)
    outcome = None
    if claimed.calibration is not None:  # a calibration job: fit first, as the child does
        outcome = apply_calibration(layout, claimed.calibration)
        layout = layout_from_mapping(outcome["layout"])
    fingerprint = build_fingerprint(layout)
    stored = store_fingerprint(fingerprint, registry.store)
    return StoredBuild(
        leds=fingerprint.n_leds,
        grid_points=fingerprint.n_cells,
        build_seconds=time.perf_counter() - started,
        matrices=stored,
        calibration=outcome,
    )


def hall_layout() -> Layout:
    """A 40 x 100 m hall, 0.5 m grid (N = 16000), 256 LEDs: ``M * N`` above the dense limit,
    so H is stored sparse (``.npz``) and neither J nor psi is stored. Builds in ~0.1 s."""
    leds = tuple(Led(x=2.5 + 2.5 * (i % 16), y=3.0 + 6.0 * (i // 16), z=3.0) for i in range(256))
    return Layout(
        room=Room(length=40.0, width=100.0, height=3.0),
        grid=Grid(step=0.5, receiver_height=0.85),
        leds=leds,
        name="Hall",
    )


def small_layout(n_leds: int = 2) -> dict[str, Any]:
    """A 2 x 2 m room with a 0.5 m grid and ``n_leds`` LEDs (sparse input, defaults omitted)."""
    return {
        "room": {"length": 2.0, "width": 2.0, "height": 3.0},
        "grid": {"step": 0.5, "receiver_height": 0.85},
        "leds": [{"x": 0.5 + 0.5 * i, "y": 1.0} for i in range(n_leds)],
    }


def overwrite(path: Path, payload: bytes) -> None:
    """Write ``payload`` over ``path`` and make the change show in its mtime.

    Two writes within one tick of a coarse filesystem clock can leave the mtime as it was;
    the matrix store would then trust its earlier check (by design: it re-hashes a file
    whose mtime or size changed, or after ``reverify_after_s``), so a test damaging a file
    states the change instead of depending on the kernel's timestamp granularity.
    """
    before = path.stat()
    os.chmod(path, 0o644)
    path.write_bytes(payload)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns + 1_000_000_000))
