"""Errors raised by the registry.

The tree::

    RegistryError                 anything the registry refuses or cannot do
    ├── NotFound                  an unknown id or version
    │   ├── RoomNotFound
    │   ├── JobNotFound
    │   ├── FingerprintNotFound   an unknown fingerprint version of a known room
    │   ├── MatrixNotFound        a matrix that is not stored (e.g. psi above the dense limit)
    │   └── EpochNotFound         an unknown epoch (or one of another room)
    ├── Conflict                  the resource's state does not allow the request
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
    "Conflict",
    "CorruptMatrix",
    "EpochClosed",
    "EpochFull",
    "EpochNotFound",
    "FingerprintNotFound",
    "FingerprintNotReady",
    "InvalidCursor",
    "JobNotFound",
    "MatrixNotFound",
    "NotFound",
    "PreconditionFailed",
    "RegistryError",
    "RegistryUnavailable",
    "RoomNotFound",
]


class RegistryError(Exception):
    """Base class of every error the registry raises."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class NotFound(RegistryError):
    """An id or version the registry does not know."""


class RoomNotFound(NotFound):
    """No room with this id."""


class JobNotFound(NotFound):
    """No job with this id (jobs go with their room)."""


class FingerprintNotFound(NotFound):
    """The room exists but has no fingerprint with this version."""


class MatrixNotFound(NotFound):
    """The fingerprint exists but this matrix was not stored (too large or unknown name)."""


class EpochNotFound(NotFound):
    """No epoch with this id in this room."""


class Conflict(RegistryError):
    """The resource's current state does not allow the request (HTTP 409)."""


class EpochClosed(Conflict):
    """The epoch's window has closed (solved, expired, failed or being solved)."""


class EpochFull(Conflict):
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
