"""Jobs test fixtures: workers on the test's registry, and a registry on a FakeClock.

With a clock that only the test moves, no lease runs out because the machine was slow: a
job is taken from a worker only when a test advances the clock past its lease.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from app.clock import FakeClock
from app.jobs import EmbeddedWorkers
from app.jobs.worker import BuildFunction
from app.registry import Registry
from app.settings import Settings

__all__ = ["clock", "job_settings", "workers"]

StartWorkers = Callable[..., EmbeddedWorkers]


@pytest.fixture
def clock() -> FakeClock:
    """The registry's (and so the workers') clock."""
    return FakeClock()


def job_settings(registry: Registry, **overrides: object) -> Settings:
    """Settings for workers on ``registry``: fast polls and heartbeats, two attempts."""
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


@pytest.fixture
def workers(registry: Registry) -> Iterator[StartWorkers]:
    """Start :class:`EmbeddedWorkers` on ``registry`` (``build=`` and settings overrides);
    every pool started is stopped after the test."""
    started: list[EmbeddedWorkers] = []

    def start(build: BuildFunction | None = None, **overrides: object) -> EmbeddedWorkers:
        settings = job_settings(registry, **overrides)
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
        pool.stop(timeout=60)
