"""Workers end to end: real builds in spawned processes, retries, crashes, shutdown.

The registry (and so every lease) runs on the FakeClock of ``conftest.py``.
"""

from __future__ import annotations

import os
import threading
import time
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select

from app.clock import FakeClock
from app.jobs import run_worker
from app.registry import Registry
from app.registry._schema import jobs
from app.registry.store import STALE_TEMPORARY_SECONDS
from app.vlp.fingerprints import Fingerprint
from app.vlp.presets import paper_layout
from tests.build_gate import BuildGate
from tests.db_fixtures import claim_next, raw_engine, small_layout
from tests.waiting import SAFETY_TIMEOUT_S, wait_for

from .builds import crash_build, endless_build
from .conftest import StartWorkers, job_settings


def lease_expiry(registry: Registry, job_id: str) -> datetime | None:
    """When the job's lease runs out, as stored."""
    with raw_engine(registry).connect() as conn:
        expiry: datetime | None = conn.execute(
            select(jobs.c.lease_expires_at).where(jobs.c.id == job_id)
        ).scalar_one()
    return expiry


@pytest.mark.slow
def test_heartbeats_keep_a_long_build_from_being_stolen(
    registry: Registry,
    clock: FakeClock,
    workers: StartWorkers,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A build held (by the gate) for longer than its lease keeps its job: the worker's
    heartbeats renew the lease, so neither a second worker nor any claim can take it."""
    gate = BuildGate(tmp_path / "gate", at=0.5)
    for name, value in gate.env().items():
        monkeypatch.setenv(name, value)  # inherited by the pools' build processes
    gate.shut()
    room = registry.create_room(name="a", layout=small_layout())
    job_id = room.job_id or ""
    lease = {"job_lease_seconds": 10.0, "job_heartbeat_seconds": 0.05}
    workers(**lease)
    assert gate.wait_held() == job_id
    claimed_at = clock.now()
    workers(**lease)  # a second worker, eager to reclaim

    def renewed_until(expiry: datetime) -> bool:
        return lease_expiry(registry, job_id) == expiry

    clock.advance(8.0)  # inside the claim's lease: a heartbeat renews it to claim + 18 s
    wait_for(lambda: renewed_until(claimed_at + timedelta(seconds=18)), "a heartbeat at 8 s")
    clock.advance(8.0)  # past the claim's lease (10 s), inside the renewal
    wait_for(lambda: renewed_until(claimed_at + timedelta(seconds=26)), "a heartbeat at 16 s")
    assert claim_next(registry, worker_id="thief") is None
    gate.open()
    wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    job = registry.get_job(job_id=job_id)
    assert (job.attempts, job.fingerprint_version) == (1, 1)
    assert [fp.version for fp in registry.list_fingerprints(room_id=room.id)] == [1]


def test_embedded_worker_builds_the_paper_room(
    registry: Registry,
    workers: StartWorkers,
    paper_fingerprint: Fingerprint,
) -> None:
    room = registry.create_room(name="Paper room", layout=paper_layout().to_mapping())
    workers()
    wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
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


def test_failing_build_is_retried_then_failed(registry: Registry, workers: StartWorkers) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    workers(max_grid_points=4)  # the room has 16 grid points
    wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "failed", "failed")
    job = registry.get_job(job_id=room.job_id or "")
    assert job.attempts == 2
    assert job.error is not None and job.error.startswith("ProblemSizeError: layout has 16")
    failed = registry.get_room(room_id=room.id)
    assert (failed.fingerprint_status, failed.fingerprint_version) == ("failed", None)


def test_crashed_build_process_is_recorded_and_pool_recovers(
    registry: Registry, workers: StartWorkers
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    workers(build=crash_build)
    wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "failed", "failed")
    job = registry.get_job(job_id=room.job_id or "")
    assert job.attempts == 2
    assert "died" in (job.error or "")


def test_stop_hands_the_running_job_back(registry: Registry, workers: StartWorkers) -> None:
    """stop() does not wait for a build: this one never ends, so a worker thread that waited
    for it would still be alive when stop() gives up joining it (after a safety timeout)."""
    room = registry.create_room(name="a", layout=small_layout())
    before = set(threading.enumerate())
    pool = workers(build=endless_build)
    threads = [t for t in set(threading.enumerate()) - before if t.name.startswith("vlp-worker")]
    wait_for(lambda: registry.get_job(job_id=room.job_id or "").status == "running", "running")
    pool.stop(timeout=SAFETY_TIMEOUT_S)
    assert threads and not any(thread.is_alive() for thread in threads)
    assert not pool.running
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_two_workers_share_the_queue(registry: Registry, workers: StartWorkers) -> None:
    rooms = [registry.create_room(name=f"r{i}", layout=small_layout(i + 1)) for i in range(4)]
    workers(embedded_workers=2)

    def all_ready() -> bool:
        return all(registry.get_room(room_id=r.id).fingerprint_status == "ready" for r in rooms)

    wait_for(all_ready, "all rooms ready")
    for index, room in enumerate(rooms):
        assert registry.get_fingerprint(room_id=room.id, version=None).leds == index + 1
        assert registry.get_job(job_id=room.job_id or "").attempts == 1


def test_run_worker_until_stopped(registry: Registry, tmp_path: Path) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    stop = threading.Event()
    thread = threading.Thread(
        target=run_worker, kwargs={"settings": job_settings(registry), "stop": stop}
    )
    thread.start()
    try:
        wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    finally:
        stop.set()
        thread.join(30)
    assert not thread.is_alive()
    assert tmp_path.exists()


def test_starting_workers_removes_stale_temporary_files(
    registry: Registry, workers: StartWorkers
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
