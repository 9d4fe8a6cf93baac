"""Frozen records that leave the registry (ORM/Core rows never do)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any, Literal

from app.vlp.fingerprints import Fingerprint

__all__ = [
    "JOB_KIND_BUILD",
    "CalibrationRecord",
    "ClaimedEpoch",
    "ClaimedJob",
    "EpochRecord",
    "EpochSettings",
    "FingerprintRecord",
    "JobRecord",
    "KeyRecord",
    "KeySource",
    "LoadedFingerprint",
    "MatrixInfo",
    "RoomRecord",
    "StoredBuild",
    "TrackChanges",
    "TrackEventRecord",
    "TrackPointRecord",
    "TrackRecord",
]

JOB_KIND_BUILD = "build_fingerprint"
KeySource = Literal["api", "environment", "generated"]


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
    """A background job (fingerprint build or calibration): the resource and the queue entry.

    ``calibration_id`` names the calibration that a ``calibration`` job runs.
    """

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
    calibration_id: str | None = None


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
    calibration_id: str | None = None
    masked_leds: tuple[int, ...] = ()


@dataclass(frozen=True)
class ClaimedJob:
    """What a worker needs to run a claimed build.

    ``layout`` is what a build job builds: the room's layout, or its active calibration's
    calibrated and masked layout (then ``calibration_id`` and ``masked_leds`` say so). A
    calibration job carries the room's nominal layout and its ``calibration`` payload (see
    :func:`app.registry._calibration_rows.calibration_payload`).
    """

    job_id: str
    room_id: str
    layout_version: int
    layout: dict[str, Any]
    attempts: int
    worker_id: str
    kind: str = JOB_KIND_BUILD
    calibration_id: str | None = None
    masked_leds: tuple[int, ...] = ()
    calibration: dict[str, Any] | None = None


@dataclass(frozen=True)
class StoredBuild:
    """A finished build whose matrix files are already in the store (sizes in bytes).

    A calibration job also returns its ``calibration`` outcome (``report``,
    ``calibrated_layout``, ``layout`` built, ``masked_leds``).
    """

    leds: int
    grid_points: int
    build_seconds: float
    matrices: dict[str, tuple[MatrixInfo, int]]
    calibration: dict[str, Any] | None = None


@dataclass(frozen=True)
class CalibrationRecord:
    """A survey calibration; its ``status`` and ``error`` are those of its job.

    ``report`` (the fit, per LED), ``masked_leds`` and ``fingerprint_version`` are set once
    the job succeeded. ``active``: builds of the room's current layout use this calibration.
    """

    id: str
    room_id: str
    layout_version: int
    job_id: str
    status: str
    error: str | None
    created_at: datetime
    finished_at: datetime | None
    request: dict[str, Any]
    based_on: str | None
    report: dict[str, Any] | None
    masked_leds: tuple[int, ...] | None
    fingerprint_version: int | None
    active: bool


@dataclass(frozen=True)
class KeyRecord:
    """A stored key (never its secret; ``key_hash`` is the sha256 hex digest)."""

    id: str
    key_hash: str
    role: str
    label: str
    source: str
    created_at: datetime
    last_used_at: datetime | None


@dataclass(frozen=True)
class EpochSettings:
    """What an epoch is created with (validated by the caller); ``track``: its solution
    updates the room's tracks."""

    model: str
    solver: str
    targets: int | None
    min_terminals: int
    max_terminals: int
    window_s: float
    fingerprint_version: int
    leds: int
    track: bool = True


@dataclass(frozen=True)
class EpochRecord:
    """An epoch as the registry holds it; ``terminals`` counts the terminals that posted."""

    id: str
    room_id: str
    status: str
    settings: EpochSettings
    terminals: int
    created_at: datetime
    expires_at: datetime
    finished_at: datetime | None
    attempts: int
    localization: dict[str, Any] | None
    error: str | None


@dataclass(frozen=True)
class ClaimedEpoch:
    """An epoch this process has claimed, with every terminal's amplitudes (None: an LED it
    did not detect) and own detection floor (None: not sent), in posting order."""

    record: EpochRecord
    owner: str
    terminal_ids: tuple[str, ...]
    amplitudes: tuple[tuple[float | None, ...], ...]
    detection_floors: tuple[float | None, ...]


@dataclass(frozen=True)
class LoadedFingerprint:
    """A fingerprint version's record and its loaded fingerprint (verified H)."""

    record: FingerprintRecord
    fingerprint: Fingerprint


@dataclass(frozen=True)
class TrackRecord:
    """A track as stored: its filter state (``filter``, the science core's arrays as lists)
    and the public summary (position, velocity, 2 x 2 position covariance in m^2, 95 %
    radius) at ``state_time``, the time of the fix that last moved it. ``last_raw`` is that
    fix (``{"x", "y", "accuracy_m"}``)."""

    id: str
    room_id: str
    terminal_id: str | None
    status: str
    filter: dict[str, Any]
    x: float
    y: float
    vx: float
    vy: float
    covariance: list[list[float]]
    accuracy_m: float
    state_time: datetime
    created_at: datetime
    updated_at: datetime
    updates: int
    misses: int
    last_raw: dict[str, float] | None


@dataclass(frozen=True)
class TrackPointRecord:
    """One point of a track's history: the state after a fix, and the fix (``raw_*``)."""

    track_id: str
    time: datetime
    x: float
    y: float
    accuracy_m: float
    raw_x: float | None = None
    raw_y: float | None = None
    raw_accuracy_m: float | None = None
    id: int | None = None


@dataclass(frozen=True)
class TrackEventRecord:
    """One event of a room's stream: ``kind`` is ``track`` (``data``: the track) or
    ``removed`` (``data``: ``{"id"}``); ``sequence`` counts a room's events from 1."""

    room_id: str
    sequence: int
    kind: str
    track_id: str
    data: dict[str, Any]
    created_at: datetime


@dataclass(frozen=True)
class TrackChanges:
    """What one update of a room's tracks writes: tracks to insert or replace, tracks that
    ended, history points, the stream events in order (``(kind, track_id, data)``), and
    the history bounds (points before ``points_before`` and events stored before
    ``events_before`` are deleted)."""

    upserts: tuple[TrackRecord, ...] = ()
    removed: tuple[str, ...] = ()
    points: tuple[TrackPointRecord, ...] = ()
    events: tuple[tuple[str, str, dict[str, Any]], ...] = ()
    points_before: datetime | None = None
    events_before: datetime | None = None
