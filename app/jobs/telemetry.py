"""Prometheus collectors shared by the API and a standalone ``vlp worker``.

A standalone worker has no HTTP API, so :func:`serve_worker_metrics` serves its metrics on
a port of their own (``vlp worker --metrics-port``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Mapping
from wsgiref.simple_server import WSGIServer

from prometheus_client import (
    GC_COLLECTOR,
    PLATFORM_COLLECTOR,
    PROCESS_COLLECTOR,
    CollectorRegistry,
    Gauge,
    start_http_server,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from app.schemas.statuses import JOB_STATUSES

__all__ = [
    "JOB_STATUSES",
    "JobsCollector",
    "WorkerMetricsServer",
    "register_process_collectors",
    "serve_worker_metrics",
]


class JobsCollector(Collector):
    """Reads the jobs-by-status counts from the registry at scrape time."""

    def __init__(self, count_jobs: Callable[[], Mapping[str, int] | None]) -> None:
        self._count_jobs = count_jobs

    def collect(self) -> Iterator[GaugeMetricFamily]:
        """One gauge sample per job status (nothing while the counts are unavailable)."""
        counts = self._count_jobs()
        if counts is None:
            return
        gauge = GaugeMetricFamily("vlp_jobs", "Fingerprint build jobs by status", labels=["status"])
        for status in JOB_STATUSES:
            gauge.add_metric([status], float(counts.get(status, 0)))
        yield gauge


def register_process_collectors(registry: CollectorRegistry) -> None:
    """Add the process (CPU, memory, open files), Python GC and platform metrics.

    The collectors read this process at scrape time; registering the library's instances
    in another registry is what its documentation does for custom registries.
    """
    for collector in (PROCESS_COLLECTOR, GC_COLLECTOR, PLATFORM_COLLECTOR):
        registry.register(collector)


class WorkerMetricsServer:
    """The running metrics endpoint of a standalone worker (``port`` is the bound one)."""

    def __init__(self, server: WSGIServer, thread: threading.Thread) -> None:
        self._server = server
        self._thread = thread
        self.port = int(server.server_port)

    def stop(self) -> None:
        """Stop serving and close the socket."""
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=10)


def serve_worker_metrics(
    *,
    host: str,
    port: int,
    count_jobs: Callable[[], Mapping[str, int] | None],
    workers: int,
) -> WorkerMetricsServer:
    """Serve ``/metrics`` of a worker process on ``host:port`` (0: any free port)."""
    registry = CollectorRegistry(auto_describe=True)
    register_process_collectors(registry)
    registry.register(JobsCollector(count_jobs))
    Gauge("vlp_worker_threads", "Build worker threads in this process", registry=registry).set(
        workers
    )
    server, thread = start_http_server(port, addr=host, registry=registry)
    return WorkerMetricsServer(server, thread)
