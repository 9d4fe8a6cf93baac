"""Connection-level functions that tie survey calibrations into the build queue.

A room's *active* calibration is its newest succeeded calibration for the room's current
layout version: ordinary builds of that layout use its calibrated (and masked) layout. A PUT
of the layout bumps ``layout_version``, so the calibration stops applying (it stays listed).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, select, update

from ._schema import calibrations, jobs
from .records import ClaimedJob

__all__ = [
    "JOB_KIND_CALIBRATION",
    "ActiveCalibration",
    "active_calibration",
    "calibration_payload",
    "claimed_job",
    "record_calibration",
]

JOB_KIND_CALIBRATION = "calibration"


@dataclass(frozen=True)
class ActiveCalibration:
    """The calibration that builds of a layout version use."""

    id: str
    calibrated_layout: dict[str, Any]
    layout: dict[str, Any]
    masked_leds: tuple[int, ...]
    report: dict[str, Any]


def active_calibration(
    conn: Connection, *, room_id: str, layout_version: int
) -> ActiveCalibration | None:
    """The newest succeeded calibration of ``(room_id, layout_version)``, or None."""
    row = conn.execute(
        select(calibrations)
        .join(jobs, jobs.c.id == calibrations.c.job_id)
        .where(
            calibrations.c.room_id == room_id,
            calibrations.c.layout_version == layout_version,
            calibrations.c.layout.is_not(None),
            jobs.c.status == "succeeded",
        )
        .order_by(calibrations.c.finished_at.desc(), calibrations.c.id.desc())
        .limit(1)
    ).one_or_none()
    if row is None:
        return None
    return ActiveCalibration(
        id=str(row.id),
        calibrated_layout=dict(row.calibrated_layout),
        layout=dict(row.layout),
        masked_leds=tuple(int(i) for i in row.masked_leds or ()),
        report=dict(row.report or {}),
    )


def calibration_payload(
    conn: Connection, *, job_id: str, room_id: str, layout_version: int
) -> tuple[str, dict[str, Any]] | None:
    """``(calibration_id, payload)`` for the child that runs a calibration job.

    The payload is the stored request plus, for a request without a survey, the active
    calibration it re-uses (``base``: its calibrated layout and report; None when the room
    was never calibrated, so the nominal model is masked). None when the row is gone.
    """
    row = conn.execute(
        select(calibrations.c.id, calibrations.c.request).where(calibrations.c.job_id == job_id)
    ).one_or_none()
    if row is None:
        return None
    payload: dict[str, Any] = {"request": dict(row.request), "base": None}
    if not payload["request"].get("survey"):
        base = active_calibration(conn, room_id=room_id, layout_version=layout_version)
        if base is not None:
            payload["base"] = {
                "id": base.id,
                "calibrated_layout": base.calibrated_layout,
                "report": base.report,
            }
            conn.execute(
                update(calibrations).where(calibrations.c.id == row.id).values(based_on=base.id)
            )
    return str(row.id), payload


def record_calibration(
    conn: Connection,
    *,
    calibration_id: str,
    outcome: dict[str, Any],
    fingerprint_version: int,
    now: datetime,
) -> None:
    """Store a finished calibration's report and layouts (in the job's completing transaction).

    ``outcome`` has ``report``, ``calibrated_layout``, ``layout`` and ``masked_leds``.
    """
    conn.execute(
        update(calibrations)
        .where(calibrations.c.id == calibration_id)
        .values(
            report=outcome["report"],
            calibrated_layout=outcome["calibrated_layout"],
            layout=outcome["layout"],
            masked_leds=list(outcome["masked_leds"]),
            fingerprint_version=fingerprint_version,
            finished_at=now,
        )
    )


def claimed_job(conn: Connection, *, job: Any, room: Any, worker_id: str) -> ClaimedJob:
    """The claimed job with what its build needs (calibrated layout, calibration payload)."""
    claimed = ClaimedJob(
        job_id=str(job.id),
        room_id=str(job.room_id),
        layout_version=int(room.layout_version),
        layout=dict(room.layout),
        attempts=int(job.attempts) + 1,
        worker_id=worker_id,
        kind=str(job.kind),
    )
    if job.kind == JOB_KIND_CALIBRATION:
        found = calibration_payload(
            conn, job_id=claimed.job_id, room_id=claimed.room_id, layout_version=room.layout_version
        )
        if found is not None:
            return replace(claimed, calibration_id=found[0], calibration=found[1])
        return claimed
    active = active_calibration(
        conn, room_id=claimed.room_id, layout_version=claimed.layout_version
    )
    if active is None:
        return claimed
    return replace(
        claimed, layout=active.layout, calibration_id=active.id, masked_leds=active.masked_leds
    )
