"""The one way tests wait: poll a condition, with a generous safety timeout.

The timeout only keeps a broken test from hanging; it is never what a test checks. A test
that needs something to happen *in time* advances a :class:`app.clock.FakeClock` instead.
"""

from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["SAFETY_TIMEOUT_S", "wait_for"]

# Long enough for a build of the 10^6-point hall on a loaded 2-core machine.
SAFETY_TIMEOUT_S = 120.0


def wait_for(
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = SAFETY_TIMEOUT_S,
    poll_s: float = 0.05,
) -> None:
    """Call ``condition`` every ``poll_s`` until it is true; fail naming ``what`` after
    ``timeout_s`` seconds (a safety timeout, not a measurement)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)
