"""Survey calibrations of a room: create (with its job), list and read.

The fit itself runs in a worker (:mod:`app.jobs.calibrate`); the queue records its outcome
(:func:`app.registry._calibration_rows.record_calibration`). A calibration applies to the
layout version it was asked for; a PUT of the layout leaves it listed but no longer active.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from sqlalchemy import Engine, select

from ._calibration_rows import JOB_KIND_CALIBRATION, active_calibration
from ._rows import locked_layout_version
from ._schema import calibrations, jobs, rooms
from .db import translate_errors, write_transaction
from .errors import PreconditionFailed, RecordNotFound, RoomNotFound
from .queue import enqueue_job
from .records import CalibrationRecord

__all__ = ["create_calibration", "get_calibration", "list_calibrations"]


def create_calibration(
    engine: Engine, *, room_id: str, layout_version: int, request: dict[str, Any], now: datetime
) -> tuple[str, str]:
    """Store a calibration request and queue its job (at ``now``); returns
    ``(calibration_id, job_id)``.

    ``request`` was validated against the room's layout at ``layout_version``.

    Raises
    ------
    RoomNotFound
    PreconditionFailed
        When the room's layout changed since it was validated (``field="layout_version"``).
    """
    calibration_id = uuid.uuid4().hex
    with write_transaction(engine) as conn:
        current = locked_layout_version(conn, room_id)
        if current != layout_version:
            raise PreconditionFailed(
                f"room {room_id} changed to layout_version {current} while the survey was "
                f"checked against version {layout_version}; send it again",
                field="layout_version",
            )
        job_id = enqueue_job(
            conn, room_id=room_id, layout_version=current, kind=JOB_KIND_CALIBRATION, now=now
        )
        conn.execute(
            calibrations.insert().values(
                id=calibration_id,
                room_id=room_id,
                layout_version=current,
                job_id=job_id,
                request=request,
                created_at=now,
            )
        )
    return calibration_id, job_id


def _select() -> Any:
    return select(
        calibrations, jobs.c.status.label("job_status"), jobs.c.error.label("job_error")
    ).select_from(calibrations.outerjoin(jobs, jobs.c.id == calibrations.c.job_id))


def _record(row: Any, active_id: str | None) -> CalibrationRecord:
    return CalibrationRecord(
        id=row.id,
        room_id=row.room_id,
        layout_version=row.layout_version,
        job_id=row.job_id,
        status=row.job_status or "failed",
        error=row.job_error,
        created_at=row.created_at,
        finished_at=row.finished_at,
        request=dict(row.request),
        based_on=row.based_on,
        report=None if row.report is None else dict(row.report),
        masked_leds=None if row.masked_leds is None else tuple(int(i) for i in row.masked_leds),
        fingerprint_version=row.fingerprint_version,
        active=row.id == active_id,
    )


def _active_id(conn: Any, room_id: str) -> str | None:
    version = conn.execute(
        select(rooms.c.layout_version).where(rooms.c.id == room_id)
    ).scalar_one_or_none()
    if version is None:
        raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
    active = active_calibration(conn, room_id=room_id, layout_version=int(version))
    return None if active is None else active.id


def list_calibrations(engine: Engine, *, room_id: str) -> list[CalibrationRecord]:
    """The room's calibrations, newest first; :class:`RoomNotFound` when unknown."""
    with translate_errors(), engine.connect() as conn:
        active_id = _active_id(conn, room_id)
        rows = conn.execute(
            _select()
            .where(calibrations.c.room_id == room_id)
            .order_by(calibrations.c.created_at.desc(), calibrations.c.id.desc())
        ).all()
    return [_record(row, active_id) for row in rows]


def get_calibration(engine: Engine, *, room_id: str, calibration_id: str) -> CalibrationRecord:
    """One calibration of the room; :class:`RecordNotFound` when the room does not have it."""
    with translate_errors(), engine.connect() as conn:
        active_id = _active_id(conn, room_id)
        row = conn.execute(
            _select().where(calibrations.c.room_id == room_id, calibrations.c.id == calibration_id)
        ).one_or_none()
    if row is None:
        raise RecordNotFound(
            f"room {room_id} has no calibration {calibration_id!r}", field="calibration_id"
        )
    return _record(row, active_id)
