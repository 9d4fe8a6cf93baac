"""The epoch sweeper: a thread that closes cooperation windows once they have passed.

Every API process runs one (from its lifespan). Each sweep calls ``sweep`` (in practice
:meth:`app.services.epoch_settler.EpochSettler.sweep`), which settles the due epochs; several
processes sweeping one registry is safe because settling claims each epoch with a
conditional update that only one of them wins. The sweeper only paces and survives errors;
it knows nothing of HTTP, so ``app.jobs`` does not import ``app.api``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from app.registry.errors import RegistryError

__all__ = ["EpochSweeper"]

_log = logging.getLogger(__name__)


class EpochSweeper:
    """Calls ``sweep`` every ``interval_s`` seconds on a daemon thread until stopped.

    Parameters
    ----------
    sweep : callable
        Settles what is due; returns how many epochs it settled.
    interval_s : float
        Pause between sweeps, seconds (> 0).
    """

    def __init__(self, *, sweep: Callable[[], int], interval_s: float) -> None:
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0 s, got {interval_s!r}")
        self._sweep = sweep
        self._interval_s = interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the thread (once)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="vlp-epoch-sweeper", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop after the sweep in progress (an epoch being solved is finished first)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def running(self) -> bool:
        """True while the thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop.wait(self._interval_s):
            try:
                self._sweep()
            except RegistryError as exc:
                # The database is away or busy: try again at the next sweep.
                _log.warning("epoch sweep skipped: %s", exc)
            except Exception:
                _log.exception("epoch sweep failed")
