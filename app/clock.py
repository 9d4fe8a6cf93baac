"""Time, injected: one clock object decides what "now" is for leases, windows and re-reads.

The lifespan (or ``vlp worker``) builds one :class:`SystemClock` and hands it to everything
that makes a decision from time: job leases and heartbeats, epoch windows, claims and sweeps,
and the fingerprint cache's version re-reads. Tests give the same places a :class:`FakeClock`
that moves only when the test advances it, so no outcome depends on how fast the machine is.

Pacing (how long a thread sleeps between polls) and safety timeouts stay on real time: they
decide when something is looked at again, never what the answer is.
"""

from __future__ import annotations

import threading
import time
from datetime import UTC, datetime, timedelta
from typing import Protocol

__all__ = ["Clock", "FakeClock", "SystemClock"]


class Clock(Protocol):
    """What the service asks of a clock."""

    def now(self) -> datetime:
        """The current time, timezone-aware UTC (stored in the registry)."""
        ...

    def monotonic(self) -> float:
        """Seconds on a clock that never goes back (intervals within one process)."""
        ...


class SystemClock:
    """The real clock: :func:`datetime.now` in UTC and :func:`time.monotonic`."""

    def now(self) -> datetime:
        """The current time, timezone-aware UTC."""
        return datetime.now(UTC)

    def monotonic(self) -> float:
        """:func:`time.monotonic`."""
        return time.monotonic()


class FakeClock:
    """A clock that stands still until :meth:`advance` moves it (thread-safe; for tests).

    Parameters
    ----------
    start : datetime, default=None
        What :meth:`now` says first (timezone-aware); the real current time when None, so
        rows it stamps sort sensibly among rows stamped by a real clock.
    """

    def __init__(self, start: datetime | None = None) -> None:
        start = datetime.now(UTC) if start is None else start
        if start.tzinfo is None:
            raise ValueError(f"start must be timezone-aware, got {start!r}")
        self._lock = threading.Lock()
        self._now = start.astimezone(UTC)
        self._monotonic = 0.0

    def now(self) -> datetime:
        """The current fake time, timezone-aware UTC."""
        with self._lock:
            return self._now

    def monotonic(self) -> float:
        """Seconds advanced since the clock was made."""
        with self._lock:
            return self._monotonic

    def advance(self, seconds: float) -> None:
        """Move both readings forward by ``seconds`` (>= 0)."""
        if not seconds >= 0:
            raise ValueError(f"a clock only moves forward; got {seconds!r} s")
        with self._lock:
            self._now += timedelta(seconds=seconds)
            self._monotonic += seconds
