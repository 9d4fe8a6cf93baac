"""Waking the readers of a room's track stream when its events move on, in every process.

Events live in the registry (``track_events``); a stream reader reads them from there, so a
reader never sees an event that was not committed and, resuming from ``Last-Event-ID``, loses
none that is kept. :class:`TrackEventHub` only says *when* to read again: this process's own
commits call :meth:`TrackEventHub.published` directly; on PostgreSQL a thread listens to the
registry's notifications (``room_id:sequence``, sent by every process's commits) and does the
same. A reader also reads again after ``poll_s`` without news (SQLite with several
processes, or a lost notification), so nothing waits for ever.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from app.registry.errors import RegistryError
from app.registry.tracks import TrackStore

__all__ = ["TrackEventHub"]

_log = logging.getLogger(__name__)
# Pause before listening again after the notification connection was lost, seconds.
_RELISTEN_S = 1.0


class TrackEventHub:
    """The newest event sequence this process knows of per room, and its waiting readers.

    Built in the lifespan, on the event loop that serves the streams (:meth:`start`).

    Parameters
    ----------
    store : TrackStore
        Whose notifications to listen to (PostgreSQL).
    poll_s : float
        The longest a reader waits without news before reading again, seconds.
    """

    def __init__(self, *, store: TrackStore, poll_s: float) -> None:
        self._store = store
        self.poll_s = poll_s
        self._latest: dict[str, int] = {}
        self._changed: dict[str, asyncio.Event] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._listener: threading.Thread | None = None

    def start(self) -> None:
        """Bind to the running event loop and, on PostgreSQL, start listening."""
        self._loop = asyncio.get_running_loop()
        if self._store.notifies:
            self._listener = threading.Thread(
                target=self._listen, name="vlp-track-listener", daemon=True
            )
            self._listener.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop listening."""
        self._stop.set()
        if self._listener is not None:
            self._listener.join(timeout)
            self._listener = None

    def published(self, room_id: str, sequence: int) -> None:
        """Room ``room_id`` has events up to ``sequence`` (thread-safe; any thread)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._advance, room_id, sequence)
        except RuntimeError:  # the loop closed meanwhile (shutting down)
            return

    def _advance(self, room_id: str, sequence: int) -> None:
        if sequence <= self._latest.get(room_id, 0):
            return
        self._latest[room_id] = sequence
        event = self._changed.pop(room_id, None)
        if event is not None:
            event.set()

    async def wait(self, room_id: str, after: int) -> None:
        """Return once the room has an event after ``after``, or after ``poll_s``."""
        if self._latest.get(room_id, 0) > after:
            return
        event = self._changed.setdefault(room_id, asyncio.Event())
        try:
            await asyncio.wait_for(event.wait(), timeout=self.poll_s)
        except TimeoutError:
            return

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                self._store.listen(self.published, self._stop)
            except RegistryError as exc:
                _log.warning("track notifications interrupted: %s", exc)
            except Exception:
                _log.exception("track notification listener failed")
            if not self._stop.is_set():
                time.sleep(_RELISTEN_S)
