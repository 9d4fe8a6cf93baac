"""Conversions between table rows and records, layout normalisation and cursors."""

from __future__ import annotations

import base64
import binascii
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, Select, select

from app.vlp.layout_mapping import layout_from_mapping

from ._schema import jobs, matrices, rooms
from .errors import InvalidCursor, RoomNotFound
from .records import FingerprintRecord, JobRecord, MatrixInfo, RoomRecord

__all__ = [
    "decode_cursor",
    "encode_cursor",
    "fingerprint_record",
    "job_record",
    "matrix_infos",
    "normalised_layout",
    "room_record",
    "room_select",
]

_STATUS_OF_JOB = {
    "queued": "pending",
    "running": "building",
    "succeeded": "ready",
    "failed": "failed",
}


def _room_columns() -> list[Any]:
    return [*rooms.c, jobs.c.status.label("job_status")]


def room_select() -> Select[Any]:
    return select(*_room_columns()).select_from(
        rooms.outerjoin(jobs, jobs.c.id == rooms.c.latest_job_id)
    )


def room_record(row: Any) -> RoomRecord:
    if row.job_status is not None:
        status = _STATUS_OF_JOB[row.job_status]
    else:
        status = "ready" if row.current_version is not None else "pending"
    return RoomRecord(
        id=row.id,
        name=row.name,
        layout=dict(row.layout),
        layout_version=row.layout_version,
        created_at=row.created_at,
        updated_at=row.updated_at,
        fingerprint_status=status,
        fingerprint_version=row.current_version,
        job_id=row.latest_job_id,
        etag=f'"{row.id}-{row.layout_version}"',
    )


def job_record(row: Any) -> JobRecord:
    return JobRecord(
        id=row.id,
        kind=row.kind,
        room_id=row.room_id,
        status=row.status,
        progress=float(row.progress),
        error=row.error,
        created_at=row.created_at,
        started_at=row.started_at,
        finished_at=row.finished_at,
        fingerprint_version=row.fingerprint_version,
        attempts=row.attempts,
        layout_version=row.layout_version,
        calibration_id=row._mapping.get("calibration_id"),
    )


def normalised_layout(name: str, layout: dict[str, Any]) -> dict[str, Any]:
    mapping = layout_from_mapping({**layout, "name": name}).to_mapping()
    return mapping


def encode_cursor(created_at: datetime, room_id: str) -> str:
    raw = f"{created_at.isoformat()}|{room_id}".encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        stamp, room_id = raw.split("|", 1)
        created_at = datetime.fromisoformat(stamp)
    except (ValueError, binascii.Error, UnicodeDecodeError) as exc:
        raise InvalidCursor(f"invalid cursor {cursor!r}", field="cursor") from exc
    if created_at.tzinfo is None:
        raise InvalidCursor(f"invalid cursor {cursor!r}", field="cursor")
    return created_at, room_id


def matrix_infos(
    conn: Connection, *, room_id: str, version: int | None
) -> dict[int, dict[str, MatrixInfo]]:
    query = select(matrices).where(matrices.c.room_id == room_id)
    if version is not None:
        query = query.where(matrices.c.version == version)
    out: dict[int, dict[str, MatrixInfo]] = {}
    for row in conn.execute(query):
        out.setdefault(row.version, {})[row.name] = MatrixInfo(
            shape=tuple(int(n) for n in row.shape), sha256=row.sha256, format=row.format
        )
    return out


def fingerprint_record(row: Any, infos: dict[str, MatrixInfo]) -> FingerprintRecord:
    return FingerprintRecord(
        version=row.version,
        room_id=row.room_id,
        layout_version=row.layout_version,
        leds=row.leds,
        grid_points=row.grid_points,
        built_at=row.built_at,
        build_seconds=float(row.build_seconds),
        matrices=dict(sorted(infos.items())),
        job_id=row.job_id,
        calibration_id=row.calibration_id,
        masked_leds=tuple(int(i) for i in row.masked_leds or ()),
    )


def locked_layout_version(conn: Connection, room_id: str) -> int:
    """The room's ``layout_version``, its row locked for the rest of the transaction.

    Raises
    ------
    RoomNotFound
    """
    version = conn.execute(
        select(rooms.c.layout_version).where(rooms.c.id == room_id).with_for_update()
    ).scalar_one_or_none()
    if version is None:
        raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
    return int(version)
