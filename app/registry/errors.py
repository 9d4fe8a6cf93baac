"""Errors raised by the registry.

The tree::

    RegistryError                 anything the registry refuses or cannot do
    ├── RecordNotFound            an unknown id or version (app.client has its own NotFound)
    │   ├── RoomNotFound
    │   ├── JobNotFound
    │   ├── FingerprintNotFound   an unknown fingerprint version of a known room
    │   ├── MatrixNotFound        a matrix that is not stored (psi above the dense limit):
    │   │                         answered 409 (it exists but is not materialised)
    │   └── EpochNotFound         an unknown epoch (or one of another room)
    ├── StateConflict             the resource's state does not allow the request
    │   ├── EpochClosed           a post to an epoch whose window has closed
    │   └── EpochFull             a new terminal in an epoch that has its maximum
    ├── PreconditionFailed        a replace against a stale ``layout_version``
    ├── FingerprintNotReady       a room with no ready fingerprint yet
    ├── CorruptMatrix             a stored matrix whose bytes no longer match its sha256
    ├── InvalidCursor             a pagination cursor the registry did not issue
    └── RegistryUnavailable       the database cannot be reached

Each message (``str(exc)``) is meant for humans and never contains SQL; database errors are
translated once, at the boundary, and chained with ``from``.
"""

from __future__ import annotations

__all__ = [
    "CorruptMatrix",
    "EpochClosed",
    "EpochFull",
    "EpochNotFound",
    "FingerprintNotFound",
    "FingerprintNotReady",
    "InvalidCursor",
    "JobNotFound",
    "MatrixNotFound",
    "PreconditionFailed",
    "RecordNotFound",
    "RegistryError",
    "RegistryUnavailable",
    "RoomNotFound",
    "StateConflict",
    "TrackNotFound",
]


class RegistryError(Exception):
    """Base class of every error the registry raises."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class RecordNotFound(RegistryError):
    """An id or version the registry does not know."""


class RoomNotFound(RecordNotFound):
    """No room with this id."""


class JobNotFound(RecordNotFound):
    """No job with this id (jobs go with their room)."""


class FingerprintNotFound(RecordNotFound):
    """The room exists but has no fingerprint with this version."""


class MatrixNotFound(RecordNotFound):
    """The fingerprint exists but this matrix was not stored (too large or unknown name)."""


class EpochNotFound(RecordNotFound):
    """No epoch with this id in this room."""


class TrackNotFound(RecordNotFound):
    """No track with this id in this room (it never existed or has ended)."""


class StateConflict(RegistryError):
    """The resource's current state does not allow the request (HTTP 409)."""


class EpochClosed(StateConflict):
    """The epoch's window has closed (solved, expired, failed or being solved)."""


class EpochFull(StateConflict):
    """The epoch already holds its maximum number of terminals."""


class PreconditionFailed(RegistryError):
    """The caller's ``layout_version`` is not the room's current one."""


class FingerprintNotReady(RegistryError):
    """The room has no ready fingerprint yet (its first build is queued, running or failed)."""


class CorruptMatrix(RegistryError):
    """A stored matrix file is missing or its sha256 does not match; a rebuild was queued."""


class InvalidCursor(RegistryError, ValueError):
    """A pagination cursor that this registry did not issue."""


class RegistryUnavailable(RegistryError):
    """The registry database cannot be reached."""
