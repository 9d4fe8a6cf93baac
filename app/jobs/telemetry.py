"""The metrics endpoint of a standalone ``vlp worker``.

A standalone worker has no HTTP API, so :func:`serve_worker_metrics` serves its metrics on
a port of their own (``vlp worker --metrics-port``): the same process and job collectors
as the API's (:mod:`app.collectors`) and its thread count.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from wsgiref.simple_server import WSGIServer

from prometheus_client import CollectorRegistry, Gauge, start_http_server

from app.collectors import JobsCollector, register_process_collectors

__all__ = ["WorkerMetricsServer", "serve_worker_metrics"]


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
