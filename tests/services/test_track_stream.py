"""The stream hub wakes a room's readers when its events move on, from any thread."""

from __future__ import annotations

import asyncio
import threading

from app.registry import Registry
from app.services.track_stream import TrackEventHub


def test_readers_wake_on_news_of_their_room_only(registry: Registry) -> None:
    async def scenario() -> tuple[bool, bool, bool]:
        hub = TrackEventHub(store=registry.tracks, poll_s=60.0)
        hub.start()
        try:
            mine = asyncio.create_task(hub.wait("room-a", 3))
            other = asyncio.create_task(hub.wait("room-b", 0))
            await asyncio.sleep(0)
            # From another thread, as a commit in the thread pool or the listener would.
            publisher = threading.Thread(target=hub.published, args=("room-a", 4))
            publisher.start()
            publisher.join()
            await asyncio.wait_for(mine, timeout=30.0)
            woke_other = other.done()
            other.cancel()
            # Already known news: no wait at all; old news does not count.
            hub.published("room-a", 2)
            await asyncio.sleep(0)
            await asyncio.wait_for(hub.wait("room-a", 3), timeout=30.0)
            stale = asyncio.create_task(hub.wait("room-a", 4))
            await asyncio.sleep(0.01)
            waiting = not stale.done()
            stale.cancel()
            return mine.done(), woke_other, waiting
        finally:
            hub.stop()

    woke, woke_other, still_waiting = asyncio.run(scenario())
    assert woke and not woke_other and still_waiting


def test_a_reader_without_news_reads_again_after_the_poll(registry: Registry) -> None:
    async def scenario() -> None:
        hub = TrackEventHub(store=registry.tracks, poll_s=0.01)
        hub.start()
        try:
            await asyncio.wait_for(hub.wait("room-a", 0), timeout=30.0)
        finally:
            hub.stop()

    asyncio.run(scenario())
