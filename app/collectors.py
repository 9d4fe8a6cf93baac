"""Prometheus collectors that the API's metrics and a standalone worker's both register.

Generic to any process of the service: the process (CPU, memory, open files), Python GC and
platform collectors, and the jobs-by-status gauge read from the registry at scrape time.
:mod:`app.telemetry` (the API) and :mod:`app.jobs.telemetry` (``vlp worker --metrics-port``)
build their ``CollectorRegistry`` from these.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

from prometheus_client import GC_COLLECTOR, PLATFORM_COLLECTOR, PROCESS_COLLECTOR, CollectorRegistry
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from app.schemas.statuses import JOB_STATUSES

__all__ = ["JobsCollector", "register_process_collectors"]


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
