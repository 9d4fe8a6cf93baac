"""Reading stored matrices: a read that finds a corrupt file queues the room's rebuild.

The registry's reads never write (:meth:`app.registry.Registry.matrix_path` only refuses a
file that fails its sha256 check); the repair is this explicit call, made by every service
path that reads a stored matrix (localize's fingerprint loads and the matrix downloads).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from app.registry import Registry
from app.registry.errors import CorruptMatrix

__all__ = ["rebuilding_if_corrupt"]


@contextmanager
def rebuilding_if_corrupt(registry: Registry, *, room_id: str) -> Iterator[None]:
    """Queue a rebuild of ``room_id`` when the block meets a :class:`CorruptMatrix` (which
    is raised again, saying so); the rebuild coalesces with one already queued."""
    try:
        yield
    except CorruptMatrix as exc:
        registry.request_build(room_id=room_id)
        raise CorruptMatrix(f"{exc.message}; a rebuild has been queued") from exc
