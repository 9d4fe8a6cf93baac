"""Workers end to end: real builds in spawned processes, retries, crashes, shutdown."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from app.jobs import EmbeddedWorkers, run_worker
from app.jobs.build import BuildTask, build_and_store
from app.registry import Registry
from app.registry.queue import StoredBuild
from app.registry.store import STALE_TEMPORARY_SECONDS
from app.settings import Settings
from app.vlp.fingerprints import Fingerprint
from app.vlp.presets import paper_layout
from tests.db_fixtures import small_layout

WAIT_S = 60.0


def _settings(registry: Registry, **overrides: object) -> Settings:
    values: dict[str, object] = {
        "data_dir": registry.data_dir,
        "database_url": registry.database_url,
        "embedded_workers": 1,
        "job_poll_seconds": 0.05,
        "job_heartbeat_seconds": 0.1,
        "job_lease_seconds": 5.0,
        "max_build_attempts": 2,
    }
    values.update(overrides)
    return Settings(**values)  # type: ignore[arg-type]


def _wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {WAIT_S} s waiting for {what}")
        time.sleep(0.05)


@pytest.fixture
def workers(registry: Registry) -> Iterator[Callable[..., EmbeddedWorkers]]:
    started: list[EmbeddedWorkers] = []

    def start(
        build: Callable[[BuildTask], StoredBuild] | None = None, **overrides: object
    ) -> EmbeddedWorkers:
        settings = _settings(registry, **overrides)
        pool = (
            EmbeddedWorkers(registry=registry, settings=settings)
            if build is None
            else EmbeddedWorkers(registry=registry, settings=settings, build=build)
        )
        pool.start()
        started.append(pool)
        return pool

    yield start
    for pool in started:
        pool.stop(timeout=10)


def crash_build(task: BuildTask) -> StoredBuild:
    """A build whose process dies."""
    del task
    os._exit(3)


def slow_build(task: BuildTask) -> StoredBuild:
    """A build that never finishes in a test's time."""
    del task
    time.sleep(60)
    raise AssertionError("unreachable")


def patient_build(task: BuildTask) -> StoredBuild:
    """A real build that takes longer than the test's job lease."""
    time.sleep(1.5)
    return build_and_store(task)


def test_heartbeats_keep_a_long_build_from_being_stolen(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    lease = {"job_lease_seconds": 0.5, "job_heartbeat_seconds": 0.1}
    workers(build=patient_build, **lease)
    _wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "running", "running")
    workers(build=patient_build, **lease)  # a second worker, eager to reclaim
    _wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.attempts, job.fingerprint_version) == (1, 1)
    assert [fp.version for fp in registry.list_fingerprints(room_id=room.id)] == [1]


def test_embedded_worker_builds_the_paper_room(
    registry: Registry,
    workers: Callable[..., EmbeddedWorkers],
    paper_fingerprint: Fingerprint,
) -> None:
    room = registry.create_room(name="Paper room", layout=paper_layout().to_mapping())
    workers()
    _wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    ready = registry.get_room(room_id=room.id)
    assert ready.fingerprint_version == 1
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.progress, job.fingerprint_version, job.attempts) == (
        "succeeded",
        1.0,
        1,
        1,
    )
    assert job.finished_at is not None and job.started_at is not None
    loaded = registry.load_fingerprint(room_id=room.id, version=1)
    assert loaded.layout == paper_fingerprint.layout
    np.testing.assert_array_equal(loaded.gains.toarray(), paper_fingerprint.gains.toarray())


def test_failing_build_is_retried_then_failed(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    workers(max_grid_points=4)  # the room has 16 grid points
    _wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "failed", "failed")
    job = registry.get_job(job_id=room.job_id or "")
    assert job.attempts == 2
    assert job.error is not None and job.error.startswith("ProblemSizeError: layout has 16")
    failed = registry.get_room(room_id=room.id)
    assert (failed.fingerprint_status, failed.fingerprint_version) == ("failed", None)


def test_crashed_build_process_is_recorded_and_pool_recovers(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    workers(build=crash_build)
    _wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "failed", "failed")
    job = registry.get_job(job_id=room.job_id or "")
    assert job.attempts == 2
    assert "died" in (job.error or "")


def test_stop_hands_the_running_job_back(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    pool = workers(build=slow_build)
    _wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "running", "running")
    started = time.monotonic()
    pool.stop(timeout=5)
    assert time.monotonic() - started < 10
    assert not pool.running
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_two_workers_share_the_queue(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    rooms = [registry.create_room(name=f"r{i}", layout=small_layout(i + 1)) for i in range(4)]
    workers(embedded_workers=2)

    def all_ready() -> bool:
        return all(registry.get_room(room_id=r.id).fingerprint_status == "ready" for r in rooms)

    _wait_for(all_ready, "all rooms ready")
    for index, room in enumerate(rooms):
        assert registry.get_fingerprint(room_id=room.id, version=None).leds == index + 1
        assert registry.get_job(job_id=room.job_id or "").attempts == 1


def test_run_worker_until_stopped(registry: Registry, tmp_path: Path) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    stop = threading.Event()
    thread = threading.Thread(
        target=run_worker, kwargs={"settings": _settings(registry), "stop": stop}
    )
    thread.start()
    try:
        _wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    finally:
        stop.set()
        thread.join(30)
    assert not thread.is_alive()
    assert tmp_path.exists()


def test_starting_workers_removes_stale_temporary_files(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    folder = registry.store.root / "ab"
    folder.mkdir(parents=True)
    stale, fresh = folder / ".tmp-dead.npy", folder / ".tmp-live.npy"
    stale.write_bytes(b"cut short by kill -9")
    fresh.write_bytes(b"still being written")
    old = time.time() - STALE_TEMPORARY_SECONDS - 60
    os.utime(stale, (old, old))
    workers()
    assert not stale.exists() and fresh.exists()
