"""Workers: threads that claim build jobs and run them in a process pool.

Each worker thread loops: claim the oldest claimable job (atomic, leased), submit the build
to a ``spawn`` process pool, renew the lease every ``job_heartbeat_seconds`` while the child
works, then record the result (or the error, retried up to ``max_build_attempts``) in one
transaction. The API process runs :class:`EmbeddedWorkers` from its lifespan; ``vlp worker``
runs :func:`run_worker`. Any number of both can share one PostgreSQL registry.

Leases are stamped with the workers' :class:`app.clock.Clock` (the registry's unless given
another); how often a thread polls and heartbeats is real time (pacing only).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.process import BaseProcess

from app.clock import Clock
from app.registry import Registry
from app.registry.errors import RegistryError
from app.registry.records import ClaimedJob, StoredBuild
from app.settings import Settings

from .build import BuildTask, build_and_store, init_build_process
from .telemetry import WorkerMetricsServer, serve_worker_metrics

__all__ = ["BuildFunction", "EmbeddedWorkers", "run_worker"]

_log = logging.getLogger(__name__)

BuildFunction = Callable[[BuildTask], StoredBuild]


class _PoolClosed(RuntimeError):
    """The pool was shut down: it starts no new build process."""


# Serialises process start-ups across pools so each pool can tell which children are its own.
_SPAWN_LOCK = threading.Lock()


class _Pool:
    """A process pool that is replaced when a child dies (``BrokenProcessPool``).

    Once shut down it refuses new builds (:class:`_PoolClosed`) instead of quietly starting
    a new executor that nobody would ever stop.
    """

    def __init__(self, size: int) -> None:
        self._size = size
        self._lock = threading.Lock()
        self._executor: ProcessPoolExecutor | None = None
        self._closed = False
        self._children: dict[int | None, BaseProcess] = {}

    def submit(self, build: BuildFunction, task: BuildTask) -> Future[StoredBuild]:
        with self._lock:
            if self._closed:
                raise _PoolClosed("the build pool is shut down")
            if self._executor is None:
                self._executor = ProcessPoolExecutor(
                    max_workers=self._size,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=init_build_process,
                )
            # ProcessPoolExecutor starts its children inside submit(); noting which children
            # appeared lets shutdown() end them through public multiprocessing calls only.
            with _SPAWN_LOCK:
                before = {child.pid for child in multiprocessing.active_children()}
                future = self._executor.submit(build, task)
                for child in multiprocessing.active_children():
                    if child.pid not in before:
                        self._children[child.pid] = child
            return future

    def discard_broken(self) -> None:
        with self._lock:
            if self._executor is not None:
                self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
            self._children.clear()  # a broken pool's children are dead or being ended

    def shutdown(self, timeout: float) -> None:
        """Stop the pool for good; children still building after ``timeout`` s are terminated.

        Their jobs were handed back to the queue (or will be reclaimed when the lease ends).
        """
        with self._lock:
            self._closed = True
            executor, self._executor = self._executor, None
            children, self._children = list(self._children.values()), {}
        if executor is None:
            return
        executor.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + timeout
        for child in children:
            child.join(max(deadline - time.monotonic(), 0.0))
            if child.is_alive():
                child.terminate()
                child.join(5.0)


class _WorkerLoop:
    """One claiming thread."""

    def __init__(
        self,
        *,
        registry: Registry,
        settings: Settings,
        pool: _Pool,
        stop: threading.Event,
        build: BuildFunction,
        clock: Clock,
    ) -> None:
        self.registry = registry
        self.settings = settings
        self.pool = pool
        self.stop = stop
        self.build = build
        self.clock = clock
        self.worker_id = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:12]}"

    def run(self) -> None:
        """Claim and run jobs until ``stop`` is set; never dies on one job's trouble."""
        while not self.stop.is_set():
            try:
                claimed = self.registry.jobs.claim(
                    worker_id=self.worker_id,
                    now=self.clock.now(),
                    lease_seconds=self.settings.job_lease_seconds,
                    max_attempts=self.settings.max_build_attempts,
                    max_per_room=self.settings.max_concurrent_builds_per_room,
                )
            except RegistryError:
                _log.warning("registry unavailable; worker %s retries", self.worker_id)
                self.stop.wait(self.settings.job_poll_seconds)
                continue
            if claimed is None:
                self.stop.wait(self.settings.job_poll_seconds)
                continue
            if self.stop.is_set():  # stopped while claiming: not this worker's job any more
                self.registry.jobs.release(claimed=claimed)
                return
            try:
                self.run_one(claimed)
            except Exception:
                # The lease runs out and another worker (or this one) takes the job again.
                _log.exception("job %s: worker error", claimed.job_id)
                self.stop.wait(self.settings.job_poll_seconds)

    def _submit(self, task: BuildTask) -> Future[StoredBuild]:
        try:
            return self.pool.submit(self.build, task)
        except BrokenProcessPool:
            self.pool.discard_broken()
            return self.pool.submit(self.build, task)

    def run_one(self, claimed: ClaimedJob) -> None:
        """Run one claimed build to its end (or hand it back when stopping)."""
        task = BuildTask(
            database_url=self.registry.database_url,
            data_dir=str(self.registry.data_dir),
            matrix_store=self.registry.matrix_store,
            job_id=claimed.job_id,
            worker_id=claimed.worker_id,
            layout=claimed.layout,
            max_cells=self.settings.max_grid_points,
            calibration=claimed.calibration,
        )
        _log.info(
            "job %s: building room %s (%s)",
            claimed.job_id,
            claimed.room_id,
            claimed.kind,
            extra=self._log_fields(claimed),
        )
        try:
            future = self._submit(task)
        except BrokenProcessPool as exc:
            self._fail(claimed, f"could not start the build process: {exc}")
            return
        except RuntimeError as exc:
            # The pool is shut down, or the interpreter is exiting ("cannot schedule new
            # futures after shutdown"): not the job's fault, so hand it back uncounted.
            _log.warning("job %s: handed back, no build process to run it: %s", claimed.job_id, exc)
            self.registry.jobs.release(claimed=claimed)
            self.stop.wait(self.settings.job_poll_seconds)
            return
        owned = True
        while True:
            try:
                result = future.result(timeout=self.settings.job_heartbeat_seconds)
                break
            except FutureTimeout:
                if self.stop.is_set():
                    future.cancel()
                    self.registry.jobs.release(claimed=claimed)
                    return
                if owned:
                    owned = self.registry.jobs.heartbeat(
                        job_id=claimed.job_id,
                        worker_id=claimed.worker_id,
                        now=self.clock.now(),
                        lease_seconds=self.settings.job_lease_seconds,
                    )
            except BrokenProcessPool:
                self.pool.discard_broken()
                self._fail(claimed, "the build process died unexpectedly")
                return
            except Exception as exc:
                self._fail(claimed, f"{type(exc).__name__}: {exc}")
                return
        version = self.registry.jobs.complete(claimed=claimed, build=result, now=self.clock.now())
        if version is None:  # lease lost or room deleted: nothing refers to the files
            self.registry.drop_unreferenced_files(
                (info.sha256, info.format) for info, _ in result.matrices.values()
            )
        _log.info(
            "job %s: done, fingerprint version %s",
            claimed.job_id,
            version,
            extra={**self._log_fields(claimed), "fingerprint_version": version},
        )

    @staticmethod
    def _log_fields(claimed: ClaimedJob) -> dict[str, object]:
        """Structured fields of a job's log lines (who built what, in which attempt)."""
        return {
            "job_id": claimed.job_id,
            "room_id": claimed.room_id,
            "worker_id": claimed.worker_id,
            "attempt": claimed.attempts,
        }

    def _fail(self, claimed: ClaimedJob, error: str) -> None:
        status = self.registry.jobs.fail(
            claimed=claimed,
            error=error,
            max_attempts=self.settings.max_build_attempts,
            now=self.clock.now(),
        )
        _log.warning(
            "job %s: attempt %d failed (%s): %s",
            claimed.job_id,
            claimed.attempts,
            status,
            error,
            extra=self._log_fields(claimed),
        )


class EmbeddedWorkers:
    """``settings.embedded_workers`` claiming threads sharing one process pool.

    Parameters
    ----------
    registry : Registry
    settings : Settings
    build : callable, default=build_and_store
        The function run in the child (a module-level function; tests swap it).
    clock : Clock, default=None
        Stamps claims, heartbeats and outcomes (the registry's clock when None).
    """

    def __init__(
        self,
        *,
        registry: Registry,
        settings: Settings,
        build: BuildFunction = build_and_store,
        clock: Clock | None = None,
    ) -> None:
        self.registry = registry
        self.settings = settings
        self.build = build
        self.clock = registry.clock if clock is None else clock
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._pool: _Pool | None = None

    def start(self, count: int | None = None) -> None:
        """Start the threads (none when ``embedded_workers`` is 0)."""
        count = self.settings.embedded_workers if count is None else count
        if count <= 0 or self._threads:
            return
        self._stop.clear()
        removed = self.registry.store.remove_stale_temporaries()
        if removed:
            _log.info("removed %d stale temporary matrix file(s)", removed)
        self._pool = _Pool(count)
        for index in range(count):
            loop = _WorkerLoop(
                registry=self.registry,
                settings=self.settings,
                pool=self._pool,
                stop=self._stop,
                build=self.build,
                clock=self.clock,
            )
            thread = threading.Thread(target=loop.run, name=f"vlp-worker-{index}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop claiming, hand running jobs back to the queue and shut the pool down."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout)
        self._threads.clear()
        if self._pool is not None:
            self._pool.shutdown(min(timeout, 2.0))
            self._pool = None

    @property
    def running(self) -> bool:
        """True while worker threads are alive."""
        return any(thread.is_alive() for thread in self._threads)


def _job_counts(registry: Registry) -> dict[str, int] | None:
    """Jobs by status for a scrape; None (no sample) while the registry is unreachable."""
    try:
        return registry.count_jobs_by_status()
    except RegistryError:
        return None


def run_worker(
    *,
    settings: Settings,
    stop: threading.Event | None = None,
    metrics_address: tuple[str, int] | None = None,
) -> None:
    """``vlp worker``: migrate, then run ``max(1, embedded_workers)`` workers until stopped.

    Without ``stop``, SIGINT and SIGTERM stop it (when called from the main thread). With
    ``metrics_address`` ``(host, port)``, Prometheus metrics (process, jobs by status) are
    served at ``http://host:port/metrics`` while it runs.
    """
    if stop is None:
        stop = threading.Event()
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                signal.signal(signum, lambda *_: stop.set())
    registry = Registry(
        database_url=settings.resolved_database_url(),
        data_dir=settings.data_dir,
        max_build_attempts=settings.max_build_attempts,
        job_lease_seconds=settings.job_lease_seconds,
        matrix_store=settings.resolved_matrix_store(),
    )
    workers = EmbeddedWorkers(registry=registry, settings=settings)
    n_workers = max(1, settings.embedded_workers)
    metrics: WorkerMetricsServer | None = None
    try:
        registry.migrate()
        if metrics_address is not None:
            host, port = metrics_address
            metrics = serve_worker_metrics(
                host=host, port=port, count_jobs=lambda: _job_counts(registry), workers=n_workers
            )
            _log.info(
                "worker metrics at http://%s:%d/metrics",
                host,
                metrics.port,
                extra={"metrics_port": metrics.port},
            )
        workers.start(n_workers)
        stop.wait()
    finally:
        workers.stop()
        if metrics is not None:
            metrics.stop()
        registry.dispose()
