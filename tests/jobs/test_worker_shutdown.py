"""Stopped workers take no jobs, end their build processes, and never fail a job for it."""

from __future__ import annotations

import multiprocessing
import threading
from multiprocessing.process import BaseProcess
from typing import Any

import pytest

from app.jobs.build import build_and_store
from app.jobs.worker import _Pool, _WorkerLoop
from app.registry import Registry
from app.registry.queue import JobQueue
from app.registry.records import ClaimedJob
from tests.db_fixtures import claim_next, small_layout
from tests.waiting import SAFETY_TIMEOUT_S, wait_for

from .builds import endless_build
from .conftest import StartWorkers, job_settings


def test_stop_ends_the_build_processes(registry: Registry, workers: StartWorkers) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    before = {child.pid for child in multiprocessing.active_children()}
    pool = workers(build=endless_build)

    def new_children() -> list[BaseProcess]:
        return [c for c in multiprocessing.active_children() if c.pid not in before]

    # The job is marked running when claimed, just before its build process starts.
    wait_for(lambda: bool(new_children()), "the build's child process")
    children = new_children()
    pool.stop(timeout=SAFETY_TIMEOUT_S)  # joins the threads; the children get 2 s, then end
    # stop() ends them (join, then terminate + join); allow the OS a moment to reap on a
    # loaded machine, but a child the pool lost track of would still be alive after this.
    wait_for(lambda: not any(child.is_alive() for child in children), "the children to end")
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_a_shut_down_pool_hands_the_job_back_uncounted(registry: Registry) -> None:
    """What a worker thread still looping during shutdown meets ("cannot schedule new
    futures after shutdown"): the job goes back to the queue, its attempt not counted."""
    room = registry.create_room(name="a", layout=small_layout())
    settings = job_settings(registry)
    pool = _Pool(1)
    pool.shutdown(timeout=0)
    loop = _WorkerLoop(
        registry=registry,
        settings=settings,
        pool=pool,
        stop=threading.Event(),
        build=build_and_store,
        clock=registry.clock,
    )
    claimed = claim_next(registry, worker_id=loop.worker_id, lease_seconds=5.0)
    assert claimed is not None and claimed.job_id == room.job_id
    loop.run_one(claimed)
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts, job.error) == ("queued", 0, None)


def test_stopped_workers_leave_new_jobs_queued(
    registry: Registry, workers: StartWorkers, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once stop() returns, the stopped threads are gone and claim nothing: a job queued
    afterwards waits for the next live worker, which takes it on its first attempt."""
    claims: list[tuple[str, ClaimedJob | None]] = []

    original_claim = JobQueue.claim

    def recorded_claim(queue: JobQueue, *, worker_id: str, **kwargs: Any) -> ClaimedJob | None:
        claimed = original_claim(queue, worker_id=worker_id, **kwargs)
        claims.append((worker_id, claimed))
        return claimed

    monkeypatch.setattr(JobQueue, "claim", recorded_claim)
    before = set(threading.enumerate())
    pool = workers()
    threads = [
        t for t in threading.enumerate() if t not in before and t.name.startswith("vlp-worker")
    ]
    wait_for(lambda: bool(claims), "the worker to poll the queue")
    pool.stop(timeout=SAFETY_TIMEOUT_S)
    assert threads and not any(thread.is_alive() for thread in threads)
    stopped = {worker_id for worker_id, _ in claims}
    polls_before_stop = len(claims)
    room = registry.create_room(name="a", layout=small_layout())
    assert registry.get_job(job_id=room.job_id or "").status == "queued"
    workers()  # a live worker
    wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
    later = claims[polls_before_stop:]
    assert not {worker_id for worker_id, _ in later} & stopped, "a stopped worker polled"
    (taker,) = [worker_id for worker_id, claimed in later if claimed is not None]
    assert taker not in stopped
    assert registry.get_job(job_id=room.job_id or "").attempts == 1


def test_workers_restart_after_stop(registry: Registry, workers: StartWorkers) -> None:
    """The same EmbeddedWorkers (one per app lifespan) can start again after a stop."""
    pool = workers()
    pool.stop(timeout=SAFETY_TIMEOUT_S)
    pool.start()
    room = registry.create_room(name="a", layout=small_layout())
    wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
