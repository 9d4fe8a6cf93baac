"""The jobs table as a queue: atomic claims, leases, retries, coalescing, per-room limits.

The registry runs on a :class:`FakeClock`: leases run out when a test advances it, never
because the machine was slow.
"""

from __future__ import annotations

import threading
from collections import Counter

import pytest

from app.clock import FakeClock
from app.registry import Registry
from app.registry.records import ClaimedJob
from tests.db_fixtures import small_layout


@pytest.fixture
def clock() -> FakeClock:
    """The registry's clock (overrides the real one of ``tests/db_fixtures.py``)."""
    return FakeClock()


def _claim(
    registry: Registry,
    worker: str,
    lease: float = 30.0,
    *,
    max_per_room: int = 1,
    room_id: str | None = None,
) -> ClaimedJob | None:
    return registry.jobs.claim(
        worker_id=worker,
        now=registry.clock.now(),
        lease_seconds=lease,
        max_attempts=3,
        max_per_room=max_per_room,
        room_id=room_id,
    )


def test_claim_takes_oldest_and_marks_running(registry: Registry, clock: FakeClock) -> None:
    first = registry.create_room(name="a", layout=small_layout())
    clock.advance(1.0)
    registry.create_room(name="b", layout=small_layout())
    claimed = _claim(registry, "w1")
    assert claimed is not None
    assert (claimed.job_id, claimed.room_id, claimed.attempts) == (first.job_id, first.id, 1)
    assert claimed.layout == first.layout
    job = registry.get_job(job_id=claimed.job_id)
    assert job.status == "running"
    assert job.started_at is not None
    assert registry.get_room(room_id=first.id).fingerprint_status == "building"


def test_concurrent_claimers_never_share_a_job(registry: Registry) -> None:
    rooms = [registry.create_room(name=f"r{i}", layout=small_layout()) for i in range(12)]
    claims: list[str] = []
    lock = threading.Lock()
    start = threading.Barrier(4)

    def claimer(name: str) -> None:
        start.wait()
        while (claimed := _claim(registry, name)) is not None:
            with lock:
                claims.append(claimed.job_id)

    threads = [threading.Thread(target=claimer, args=(f"w{i}",)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert Counter(claims).most_common(1)[0][1] == 1
    assert sorted(claims) == sorted(room.job_id or "" for room in rooms)


def test_expired_lease_is_reclaimed_and_old_owner_is_fenced(
    registry: Registry, clock: FakeClock
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    first = _claim(registry, "dead", lease=10.0)
    assert first is not None
    clock.advance(9.999)
    assert _claim(registry, "other") is None  # lease still valid
    clock.advance(0.002)
    second = _claim(registry, "other")
    assert second is not None
    assert (second.job_id, second.attempts) == (first.job_id, 2)
    now = clock.now()
    assert not registry.jobs.heartbeat(
        job_id=first.job_id, worker_id="dead", now=now, lease_seconds=30
    )
    assert not registry.jobs.report_progress(job_id=first.job_id, worker_id="dead", progress=0.5)
    assert registry.jobs.fail(claimed=first, error="late", max_attempts=3, now=now) is None
    assert registry.jobs.heartbeat(
        job_id=second.job_id, worker_id="other", now=now, lease_seconds=30
    )
    assert registry.jobs.report_progress(job_id=second.job_id, worker_id="other", progress=0.25)
    assert registry.get_job(job_id=room.job_id or "").progress == pytest.approx(0.25)


def test_heartbeat_keeps_the_lease(registry: Registry, clock: FakeClock) -> None:
    registry.create_room(name="a", layout=small_layout())
    claimed = _claim(registry, "w", lease=10.0)
    assert claimed is not None
    for _ in range(3):  # each heartbeat comes 8 s after the last: in time, never early
        clock.advance(8.0)
        assert registry.jobs.heartbeat(
            job_id=claimed.job_id,
            worker_id="w",
            now=clock.now(),
            lease_seconds=10.0,
        )
    clock.advance(8.0)  # 32 s after the claim: long past its lease, not past the last renewal
    assert _claim(registry, "thief") is None
    clock.advance(2.001)  # the last renewal runs out
    stolen = _claim(registry, "thief")
    assert stolen is not None and (stolen.job_id, stolen.attempts) == (claimed.job_id, 2)


def test_lost_worker_exhausts_attempts(registry: Registry, clock: FakeClock) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    for _ in range(3):
        assert _claim(registry, "dies", lease=5.0) is not None
        clock.advance(5.001)
    assert _claim(registry, "late") is None
    job = registry.get_job(job_id=room.job_id or "")
    assert job.status == "failed"
    assert job.attempts == 3
    assert "lease expired" in (job.error or "")
    assert registry.get_room(room_id=room.id).fingerprint_status == "failed"


def test_failures_are_retried_then_failed_with_error(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    statuses = []
    for attempt in range(1, 4):
        claimed = _claim(registry, "w")
        assert claimed is not None
        assert claimed.attempts == attempt
        statuses.append(
            registry.jobs.fail(
                claimed=claimed,
                error=f"boom {attempt}",
                max_attempts=3,
                now=registry.clock.now(),
            )
        )
    assert statuses == ["queued", "queued", "failed"]
    assert _claim(registry, "w") is None
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.error, job.attempts) == ("failed", "boom 3", 3)
    assert job.finished_at is not None
    assert registry.get_room(room_id=room.id).fingerprint_status == "failed"


def test_release_returns_job_without_counting(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    claimed = _claim(registry, "w")
    assert claimed is not None
    assert registry.jobs.release(claimed=claimed)
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_rebuilds_are_coalesced(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    assert registry.request_build(room_id=room.id).id == room.job_id
    claimed = _claim(registry, "w")
    assert claimed is not None
    running = registry.request_build(room_id=room.id)
    assert (running.id, running.status) == (room.job_id, "running")
    registry.replace_room(
        room_id=room.id, name="a", layout=small_layout(3), expected_layout_version=1
    )
    newer = registry.get_room(room_id=room.id)
    assert newer.job_id != room.job_id
    assert registry.request_build(room_id=room.id).id == newer.job_id


def test_one_live_build_per_room(registry: Registry) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    assert _claim(registry, "w1") is not None
    registry.replace_room(
        room_id=room.id, name="a", layout=small_layout(3), expected_layout_version=1
    )
    assert _claim(registry, "w2") is None
    assert _claim(registry, "w2", max_per_room=2) is not None


def test_stale_running_job_is_superseded(registry: Registry, clock: FakeClock) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    stale = _claim(registry, "dead", lease=5.0)
    assert stale is not None
    clock.advance(1.0)  # the replacement's job is the younger one
    registry.replace_room(
        room_id=room.id, name="a", layout=small_layout(3), expected_layout_version=1
    )
    assert _claim(registry, "w") is None  # the dead owner's lease still holds the room
    clock.advance(4.001)
    fresh = _claim(registry, "w")
    assert fresh is not None
    assert (fresh.layout_version, len(fresh.layout["leds"])) == (2, 3)
    old = registry.get_job(job_id=stale.job_id)
    assert old.status == "failed"
    assert "superseded" in (old.error or "")


def test_claim_for_one_room(registry: Registry) -> None:
    registry.create_room(name="a", layout=small_layout())
    second = registry.create_room(name="b", layout=small_layout())
    claimed = _claim(registry, "w", room_id=second.id)
    assert claimed is not None
    assert claimed.room_id == second.id


def test_count_jobs_by_status(registry: Registry, clock: FakeClock) -> None:
    assert registry.count_jobs_by_status() == {
        "queued": 0,
        "running": 0,
        "succeeded": 0,
        "failed": 0,
    }
    for name in "abc":
        registry.create_room(name=name, layout=small_layout())
    claimed = _claim(registry, "w")
    assert claimed is not None
    registry.jobs.fail(claimed=claimed, error="x", max_attempts=1, now=clock.now())
    assert _claim(registry, "w") is not None
    assert registry.count_jobs_by_status() == {
        "queued": 1,
        "running": 1,
        "succeeded": 0,
        "failed": 1,
    }
