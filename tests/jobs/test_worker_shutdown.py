"""Stopped workers take no jobs, end their build processes, and never fail a job for it."""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Callable
from multiprocessing.process import BaseProcess

from app.jobs import EmbeddedWorkers
from app.jobs.build import build_and_store
from app.jobs.worker import _Pool, _WorkerLoop
from app.registry import Registry
from tests.db_fixtures import claim_next, small_layout

from .test_worker import _settings, _wait_for, slow_build, workers

__all__ = ["workers"]


def test_stop_ends_the_build_processes(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    room = registry.create_room(name="a", layout=small_layout())
    before = {child.pid for child in multiprocessing.active_children()}
    pool = workers(build=slow_build)

    def new_children() -> list[BaseProcess]:
        return [c for c in multiprocessing.active_children() if c.pid not in before]

    # The job is marked running when claimed, just before its build process starts.
    _wait_for(lambda: bool(new_children()), "the build's child process")
    children = new_children()
    pool.stop(timeout=1)
    # stop() ends them (join, then terminate + join); allow the OS a moment to reap on a
    # loaded machine, but a child the pool lost track of would still be alive after this.
    _wait_for(lambda: not any(child.is_alive() for child in children), "the children to end")
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_a_shut_down_pool_hands_the_job_back_uncounted(registry: Registry) -> None:
    """What a worker thread still looping during shutdown meets ("cannot schedule new
    futures after shutdown"): the job goes back to the queue, its attempt not counted."""
    room = registry.create_room(name="a", layout=small_layout())
    settings = _settings(registry)
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
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    pool = workers()
    pool.stop(timeout=5)
    assert not pool.running
    room = registry.create_room(name="a", layout=small_layout())
    time.sleep(20 * _settings(registry).job_poll_seconds)  # many polls of a live worker
    job = registry.get_job(job_id=room.job_id or "")
    assert (job.status, job.attempts) == ("queued", 0)


def test_workers_restart_after_stop(
    registry: Registry, workers: Callable[..., EmbeddedWorkers]
) -> None:
    """The same EmbeddedWorkers (one per app lifespan) can start again after a stop."""
    pool = workers()
    pool.stop(timeout=5)
    pool.start()
    room = registry.create_room(name="a", layout=small_layout())
    _wait_for(lambda: registry.get_room(room_id=room.id).fingerprint_status == "ready", "ready")
