"""An in-process LRU of rendered PNGs, bounded by entry count and total bytes.

Keys name everything a picture depends on: the room, the fingerprint version (immutable) or,
for a room without a ready fingerprint, its layout version, and the drawing options. So an
entry never goes stale; a new version simply makes a new key. Each API process keeps its own.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

__all__ = ["CachedPicture", "PictureCache"]

PictureKey = tuple[object, ...]


@dataclass(frozen=True)
class CachedPicture:
    """PNG bytes and their strong ``ETag`` (quoted sha256 prefix)."""

    png: bytes
    etag: str


class PictureCache:
    """Thread-safe LRU of :class:`CachedPicture` (``hits`` and ``misses`` count lookups).

    Parameters
    ----------
    max_entries : int, default=64
    max_bytes : int, default=64 MiB
    """

    def __init__(self, *, max_entries: int = 64, max_bytes: int = 64 * 2**20) -> None:
        self._max_entries = max_entries
        self._max_bytes = max_bytes
        self._entries: OrderedDict[PictureKey, CachedPicture] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def get(self, key: PictureKey) -> CachedPicture | None:
        """The cached picture of ``key`` (marked most recently used), or None."""
        with self._lock:
            found = self._entries.get(key)
            if found is None:
                self.misses += 1
                return None
            self._entries.move_to_end(key)
            self.hits += 1
            return found

    def put(self, key: PictureKey, png: bytes) -> CachedPicture:
        """Store ``png`` under ``key`` (evicting the least recently used) and return it."""
        picture = CachedPicture(png=png, etag=f'"{hashlib.sha256(png).hexdigest()[:32]}"')
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= len(old.png)
            self._entries[key] = picture
            self._bytes += len(png)
            while self._entries and (
                len(self._entries) > self._max_entries or self._bytes > self._max_bytes
            ):
                _, dropped = self._entries.popitem(last=False)
                self._bytes -= len(dropped.png)
        return picture

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
