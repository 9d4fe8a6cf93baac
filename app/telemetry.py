"""Prometheus metrics of one app (its own ``CollectorRegistry``, nothing global)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping

from prometheus_client import CollectorRegistry, Counter, Histogram, Info

from app.collectors import JobsCollector, register_process_collectors

__all__ = ["Metrics"]

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class Metrics:
    """Request, localization, cache and process metrics of one app."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        register_process_collectors(self.registry)
        # Which process answered: `vlp serve --workers N` runs N of them on one port.
        self.process = Info(
            "vlp_api_process", "The API process that answered", registry=self.registry
        )
        self.process.info({"pid": str(os.getpid())})
        self.requests = Counter(
            "vlp_http_requests",
            "HTTP requests by route template",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "vlp_http_request_duration_seconds",
            "HTTP request latency by route template",
            ["method", "route"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.localize_latency = Histogram(
            "vlp_localize_duration_seconds",
            "Solver time of localize requests",
            ["solver", "model"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.cache = Counter(
            "vlp_fingerprint_cache",
            "Fingerprint/solver cache lookups",
            ["result"],
            registry=self.registry,
        )

        self.epochs = Counter(
            "vlp_epochs_settled",
            "Epochs this process closed, by outcome (each epoch is settled by one process)",
            ["status"],
            registry=self.registry,
        )

    def watch_jobs(self, count_jobs: Callable[[], Mapping[str, int] | None]) -> None:
        """Expose jobs by status, read through ``count_jobs`` at each scrape."""
        self.registry.register(JobsCollector(count_jobs))
