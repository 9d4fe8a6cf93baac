"""The registry: rooms, API keys, fingerprint metadata and the matrix store.

Rows never leave this module: every method returns frozen records from
:mod:`app.registry.records`. All methods are keyword-only. The registry owns one door per
other concern on the same database: :attr:`Registry.jobs` (:class:`~app.registry.queue.JobQueue`:
claim, heartbeat, finish, used by :mod:`app.jobs`) and :attr:`Registry.epochs`
(:class:`~app.registry.epochs.EpochStore`) and :attr:`Registry.tracks`
(:class:`~app.registry.tracks.TrackStore`); nothing outside this package touches the engine.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from sqlalchemy import Engine, delete, func, insert, select, text, update

from app.clock import Clock, SystemClock
from app.schemas.statuses import JOB_STATUSES
from app.vlp.fingerprints import Fingerprint
from app.vlp.layout_mapping import layout_from_mapping

from . import keys as _keys
from ._rows import (
    decode_cursor,
    encode_cursor,
    fingerprint_record,
    job_record,
    locked_layout_version,
    matrix_infos,
    normalised_layout,
    room_record,
    room_select,
)
from ._schema import calibrations, fingerprints, jobs, matrices, rooms
from .blob_store import MatrixStorage, MatrixStoreKind, open_matrix_store
from .calibrations import create_calibration, get_calibration, list_calibrations
from .db import (
    create_registry_engine,
    migrate,
    migrations_current,
    translate_errors,
    write_transaction,
)
from .epochs import EpochStore
from .errors import (
    CorruptMatrix,
    FingerprintNotFound,
    FingerprintNotReady,
    JobNotFound,
    MatrixNotFound,
    PreconditionFailed,
    RoomNotFound,
)
from .queue import JobQueue, enqueue_build
from .records import (
    CalibrationRecord,
    FingerprintRecord,
    JobRecord,
    KeyRecord,
    KeySource,
    LoadedFingerprint,
    RoomRecord,
)
from .tracks import TrackStore

__all__ = ["Registry"]


class Registry:
    """Rooms, API keys, fingerprints, build jobs and epochs, in SQLite or PostgreSQL.

    A room's ``fingerprint_status`` is that of its latest build job (``queued`` ->
    ``pending``, ``running`` -> ``building``, ``succeeded`` -> ``ready``, ``failed`` ->
    ``failed``); ``fingerprint_version`` is the last version that became current and is what
    localization uses, so a failed rebuild keeps serving the previous version. A version
    becomes current only when its build finished, in the transaction that records it, and only
    if it was built from the room's current layout.

    Parameters
    ----------
    database_url : str
        SQLAlchemy URL (``sqlite:///...`` or ``postgresql+psycopg://...``).
    data_dir : Path
        The matrix files (or, with the ``database`` store, their verified local cache) live in
        ``data_dir / "matrices"``.
    max_build_attempts : int, default=3
    job_lease_seconds : float, default=30.0
    matrix_store : {"files", "database"}, default="files"
        Where matrix files are kept: on the local disk only, or in the registry database so
        that hosts sharing only the database serve the same rooms (``Settings`` picks
        ``database`` for PostgreSQL unless told otherwise).
    clock : Clock, default=None
        What "now" is for the rows it stamps and the epoch windows it checks; a
        :class:`app.clock.SystemClock` when None. Workers, the epoch settler and the
        fingerprint cache built on this registry use the same clock unless given another.
    """

    def __init__(
        self,
        *,
        database_url: str,
        data_dir: Path,
        max_build_attempts: int = 3,
        job_lease_seconds: float = 30.0,
        matrix_store: MatrixStoreKind = "files",
        clock: Clock | None = None,
    ) -> None:
        self.database_url = database_url
        self.clock: Clock = SystemClock() if clock is None else clock
        self.data_dir = data_dir
        self.max_build_attempts = max_build_attempts
        self.job_lease_seconds = job_lease_seconds
        self._engine: Engine = create_registry_engine(database_url)
        self.matrix_store: MatrixStoreKind = matrix_store
        self.store: MatrixStorage = open_matrix_store(
            matrix_store, data_dir=data_dir, engine=self._engine
        )
        self.jobs = JobQueue(self._engine)
        self.epochs = EpochStore(self._engine)
        self.tracks = TrackStore(self._engine)

    # -- lifecycle ------------------------------------------------------------------------
    def migrate(self) -> None:
        """Apply the Alembic migrations up to head (idempotent, safe concurrently)."""
        migrate(self._engine)

    def ping(self) -> None:
        """Raise :class:`RegistryUnavailable` when the database does not answer."""
        with translate_errors(), self._engine.connect() as conn:
            conn.execute(text("SELECT 1"))

    def migrations_current(self) -> bool:
        """True when the schema is at the newest migration."""
        return migrations_current(self._engine)

    def dispose(self) -> None:
        """Close every pooled connection."""
        self._engine.dispose()

    # -- API keys (rules in app.registry.keys) ----------------------------------------------
    def create_api_key(
        self, *, key_hash: str, role: str, label: str, source: KeySource = "api"
    ) -> KeyRecord:
        """Store a new key by its sha256 hex hash."""
        return _keys.create_api_key(
            self._engine, key_hash=key_hash, role=role, label=label, source=source
        )

    def list_api_keys(self) -> list[KeyRecord]:
        """The keys in force, oldest first."""
        return _keys.list_api_keys(self._engine)

    def get_active_key(self, *, key_hash: str) -> KeyRecord | None:
        """The key in force with this hash, or None."""
        return _keys.get_active_key(self._engine, key_hash=key_hash)

    def revoke_api_key(self, *, key_id: str) -> KeyRecord:
        """Revoke a key in force (RecordNotFound; StateConflict for the last admin key)."""
        return _keys.revoke_api_key(self._engine, key_id=key_id)

    def touch_api_key(self, *, key_hash: str, when: datetime) -> None:
        """Record the key's last use."""
        _keys.touch_api_key(self._engine, key_hash=key_hash, when=when)

    def sync_environment_keys(
        self, *, configured: list[tuple[str, str]]
    ) -> tuple[list[str], list[str]]:
        """Make the stored environment keys those configured (see app.registry.keys)."""
        return _keys.sync_environment_keys(self._engine, configured=configured)

    def add_generated_keys_if_no_admin(self, *, keys: list[tuple[str, str]]) -> bool:
        """Store these ``(key_hash, role)`` as generated keys unless an admin key is in force."""
        return _keys.add_generated_keys_if_no_admin(self._engine, keys=keys)

    def count_active_admin_keys(self) -> int:
        """How many admin keys are in force."""
        return _keys.count_active_admin_keys(self._engine)

    # -- rooms ----------------------------------------------------------------------------
    def create_room(self, *, name: str, layout: dict[str, Any]) -> RoomRecord:
        """Store a room (layout validated and defaults applied) and queue its first build.

        Raises
        ------
        app.vlp.errors.GeometryError
            When the layout is not valid.
        """
        mapping = normalised_layout(name, layout)
        room_id = uuid.uuid4().hex
        now = self.clock.now()
        with write_transaction(self._engine) as conn:
            conn.execute(
                insert(rooms).values(
                    id=room_id,
                    name=name,
                    layout=mapping,
                    layout_version=1,
                    created_at=now,
                    updated_at=now,
                )
            )
            enqueue_build(conn, room_id=room_id, layout_version=1, now=now)
        return self.get_room(room_id=room_id)

    def list_rooms(self, *, limit: int, cursor: str | None) -> tuple[list[RoomRecord], str | None]:
        """Rooms in creation order (ties by id), ``limit`` at a time, and the next cursor."""
        query = room_select().order_by(rooms.c.created_at, rooms.c.id).limit(limit + 1)
        if cursor is not None:
            created_at, room_id = decode_cursor(cursor)
            query = query.where(
                (rooms.c.created_at > created_at)
                | ((rooms.c.created_at == created_at) & (rooms.c.id > room_id))
            )
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(query).all()
        records = [room_record(row) for row in rows[:limit]]
        if len(rows) <= limit or not records:
            return records, None
        last = records[-1]
        return records, encode_cursor(last.created_at, last.id)

    def get_room(self, *, room_id: str) -> RoomRecord:
        """One room; :class:`RoomNotFound` when unknown."""
        with translate_errors(), self._engine.connect() as conn:
            row = conn.execute(room_select().where(rooms.c.id == room_id)).one_or_none()
        if row is None:
            raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
        return room_record(row)

    def replace_room(
        self, *, room_id: str, name: str, layout: dict[str, Any], expected_layout_version: int
    ) -> RoomRecord:
        """Replace name and layout in one transaction if ``expected_layout_version`` is current.

        Raises
        ------
        RoomNotFound, PreconditionFailed, app.vlp.errors.GeometryError
        """
        mapping = normalised_layout(name, layout)
        now = self.clock.now()
        with write_transaction(self._engine) as conn:
            current = locked_layout_version(conn, room_id)
            if current != expected_layout_version:
                raise PreconditionFailed(
                    f"room {room_id} is at layout_version {current}, "
                    f"the request expected {expected_layout_version}",
                    field="If-Match",
                )
            conn.execute(
                update(rooms)
                .where(rooms.c.id == room_id)
                .values(name=name, layout=mapping, layout_version=current + 1, updated_at=now)
            )
            enqueue_build(conn, room_id=room_id, layout_version=current + 1, now=now)
        return self.get_room(room_id=room_id)

    def delete_room(self, *, room_id: str) -> None:
        """Delete the room, its jobs and fingerprints, and matrix files nobody else uses."""
        with write_transaction(self._engine) as conn:
            files = conn.execute(
                select(matrices.c.sha256, matrices.c.format)
                .where(matrices.c.room_id == room_id)
                .distinct()
            ).all()
            conn.execute(delete(matrices).where(matrices.c.room_id == room_id))
            conn.execute(delete(fingerprints).where(fingerprints.c.room_id == room_id))
            conn.execute(delete(calibrations).where(calibrations.c.room_id == room_id))
            conn.execute(delete(jobs).where(jobs.c.room_id == room_id))
            deleted = conn.execute(delete(rooms).where(rooms.c.id == room_id)).rowcount
        if not deleted:
            raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
        self.drop_unreferenced_files((sha256, fmt) for sha256, fmt in files)

    def drop_unreferenced_files(self, files: Iterable[tuple[str, str]]) -> None:
        """Delete those ``(sha256, format)`` files that no stored matrix refers to."""
        with translate_errors(), self._engine.connect() as conn:
            for sha256, fmt in files:
                users = conn.execute(
                    select(func.count()).select_from(matrices).where(matrices.c.sha256 == sha256)
                ).scalar_one()
                if not users:
                    self.store.delete(sha256, fmt)

    def count_rooms(self) -> int:
        """How many rooms exist."""
        with translate_errors(), self._engine.connect() as conn:
            return int(conn.execute(select(func.count()).select_from(rooms)).scalar_one())

    # -- builds ---------------------------------------------------------------------------
    def request_build(self, *, room_id: str) -> JobRecord:
        """Queue a build of the room's layout, or return the queued/running one for it."""
        with write_transaction(self._engine) as conn:
            version = locked_layout_version(conn, room_id)
            job_id = enqueue_build(
                conn, room_id=room_id, layout_version=version, now=self.clock.now()
            )
        return self.get_job(job_id=job_id)

    def count_jobs_by_status(self) -> dict[str, int]:
        """How many jobs are in each status (all four keys, zeros included), for metrics."""
        counts: dict[str, int] = dict.fromkeys(JOB_STATUSES, 0)
        with translate_errors(), self._engine.connect() as conn:
            for status, count in conn.execute(
                select(jobs.c.status, func.count()).group_by(jobs.c.status)
            ):
                counts[str(status)] = int(count)
        return counts

    def get_job(self, *, job_id: str) -> JobRecord:
        """One job; :class:`JobNotFound` when unknown (jobs go with their room)."""
        with translate_errors(), self._engine.connect() as conn:
            row = conn.execute(
                select(jobs, calibrations.c.id.label("calibration_id"))
                .select_from(jobs.outerjoin(calibrations, calibrations.c.job_id == jobs.c.id))
                .where(jobs.c.id == job_id)
            ).one_or_none()
        if row is None:
            raise JobNotFound(f"no job with id {job_id!r}", field="job_id")
        return job_record(row)

    # -- calibrations ---------------------------------------------------------------------
    def create_calibration(
        self, *, room_id: str, layout_version: int, request: dict[str, Any]
    ) -> CalibrationRecord:
        """Store a calibration request checked against ``layout_version`` and queue its job.

        Raises
        ------
        RoomNotFound, PreconditionFailed (the layout changed meanwhile)
        """
        calibration_id, _ = create_calibration(
            self._engine,
            room_id=room_id,
            layout_version=layout_version,
            request=request,
            now=self.clock.now(),
        )
        return self.get_calibration(room_id=room_id, calibration_id=calibration_id)

    def list_calibrations(self, *, room_id: str) -> list[CalibrationRecord]:
        """The room's calibrations, newest first."""
        return list_calibrations(self._engine, room_id=room_id)

    def get_calibration(self, *, room_id: str, calibration_id: str) -> CalibrationRecord:
        """One calibration of the room (RecordNotFound when unknown)."""
        return get_calibration(self._engine, room_id=room_id, calibration_id=calibration_id)

    # -- fingerprints ---------------------------------------------------------------------
    def list_fingerprints(self, *, room_id: str) -> list[FingerprintRecord]:
        """The room's fingerprint versions, newest first."""
        self.get_room(room_id=room_id)
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(
                select(fingerprints)
                .where(fingerprints.c.room_id == room_id)
                .order_by(fingerprints.c.version.desc())
            ).all()
            infos = matrix_infos(conn, room_id=room_id, version=None)
        return [fingerprint_record(row, infos.get(row.version, {})) for row in rows]

    def get_fingerprint(self, *, room_id: str, version: int | None) -> FingerprintRecord:
        """One version's metadata; ``version=None`` means the current one.

        Raises
        ------
        RoomNotFound, FingerprintNotReady (no current version), FingerprintNotFound
        """
        return self._fingerprint_row(room_id=room_id, version=version)[0]

    def _fingerprint_row(
        self, *, room_id: str, version: int | None
    ) -> tuple[FingerprintRecord, Any]:
        # The record and its row (which holds the layout snapshot), in one read.
        if version is None:
            version = self.current_version(room_id=room_id)
            if version is None:
                raise FingerprintNotReady(
                    f"room {room_id} has no ready fingerprint yet", field="fingerprint_version"
                )
        with translate_errors(), self._engine.connect() as conn:
            row = conn.execute(
                select(fingerprints).where(
                    fingerprints.c.room_id == room_id, fingerprints.c.version == version
                )
            ).one_or_none()
            infos = matrix_infos(conn, room_id=room_id, version=version)
        if row is None:
            self.get_room(room_id=room_id)
            raise FingerprintNotFound(
                f"room {room_id} has no fingerprint version {version}", field="version"
            )
        return fingerprint_record(row, infos.get(version, {})), row

    def current_version(self, *, room_id: str) -> int | None:
        """The version localization uses now (one indexed read); RoomNotFound when unknown."""
        with translate_errors(), self._engine.connect() as conn:
            row = conn.execute(
                select(rooms.c.current_version).where(rooms.c.id == room_id)
            ).one_or_none()
        if row is None:
            raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
        return None if row.current_version is None else int(row.current_version)

    def matrix_path(self, *, room_id: str, version: int, name: str) -> Path:
        """The verified file of one stored matrix (a read: it never queues anything).

        Raises
        ------
        FingerprintNotFound, MatrixNotFound
            Unknown version, or a matrix that was not stored (e.g. psi above the limit).
        CorruptMatrix
            The file is missing or its sha256 does not match; the caller decides whether to
            queue a rebuild (:meth:`request_build`).
        """
        record = self.get_fingerprint(room_id=room_id, version=version)
        return self._verified_path(record, name)

    def _verified_path(self, record: FingerprintRecord, name: str) -> Path:
        info = record.matrices.get(name)
        if info is None:
            raise MatrixNotFound(
                f"fingerprint {record.version} of room {record.room_id} has no stored matrix "
                f"{name!r}",
                field="matrix",
            )
        path = self.store.verified_path(info.sha256, info.format)
        if path is None:
            raise CorruptMatrix(
                f"matrix {name} of fingerprint {record.version} of room {record.room_id} "
                "failed its sha256 check"
            )
        return path

    def load_fingerprint(self, *, room_id: str, version: int) -> Fingerprint:
        """The fingerprint of that version (see :meth:`load_version`)."""
        return self.load_version(room_id=room_id, version=version).fingerprint

    def load_version(self, *, room_id: str, version: int) -> LoadedFingerprint:
        """One version's record and its fingerprint (layout snapshot and verified H), from
        one read of its row.

        Raises
        ------
        RoomNotFound, FingerprintNotFound, MatrixNotFound, CorruptMatrix
        """
        record, row = self._fingerprint_row(room_id=room_id, version=version)
        path = self._verified_path(record, "H")
        if path.suffix == ".npz":
            gains = sp.csr_array(sp.load_npz(path))
        else:
            gains = sp.csr_array(np.load(path, allow_pickle=False))
        gains.sort_indices()
        fingerprint = Fingerprint(layout=layout_from_mapping(row.layout), gains=gains)
        return LoadedFingerprint(record=record, fingerprint=fingerprint)
