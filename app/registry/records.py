"""Frozen records that leave the registry (ORM/Core rows never do)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

__all__ = ["FingerprintRecord", "JobRecord", "MatrixInfo", "RoomRecord"]


@dataclass(frozen=True)
class RoomRecord:
    """A room as the registry holds it.

    ``fingerprint_status`` is derived from the room's latest build job: ``queued`` ->
    ``"pending"``, ``running`` -> ``"building"``, ``succeeded`` -> ``"ready"``, ``failed`` ->
    ``"failed"`` (a room with no job is ``"ready"`` when it has a version, else ``"pending"``).
    ``fingerprint_version`` is independent of it: the last version that became current, which
    localization uses. So a failed or pending rebuild keeps serving the older version.
    """

    id: str
    name: str
    layout: dict[str, Any]
    layout_version: int
    created_at: datetime
    updated_at: datetime
    fingerprint_status: str
    fingerprint_version: int | None
    job_id: str | None
    etag: str


@dataclass(frozen=True)
class JobRecord:
    """A fingerprint build job: both the public resource and the queue entry."""

    id: str
    kind: str
    room_id: str | None
    status: str
    progress: float
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    fingerprint_version: int | None
    attempts: int
    layout_version: int


@dataclass(frozen=True)
class MatrixInfo:
    """One stored matrix: its shape, the sha256 of the file's bytes and ``"npy"``/``"npz"``."""

    shape: tuple[int, ...]
    sha256: str
    format: str


@dataclass(frozen=True)
class FingerprintRecord:
    """An immutable fingerprint version of a room."""

    version: int
    room_id: str
    layout_version: int
    leds: int
    grid_points: int
    built_at: datetime
    build_seconds: float
    matrices: dict[str, MatrixInfo]
    job_id: str | None
