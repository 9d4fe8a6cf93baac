"""The jobs table as a durable queue: enqueue (coalescing), claim, heartbeat, finish.

Claiming is atomic: ``SELECT ... FOR UPDATE SKIP LOCKED`` on PostgreSQL, a ``BEGIN IMMEDIATE``
transaction on SQLite. A claimed job carries a lease (``lease_owner``, ``lease_expires_at``)
that the worker renews with heartbeats; a ``running`` job whose lease expired is claimable
again, so a job of a worker that died is picked up by another one. Every state change of a
job is guarded by ``lease_owner`` so a worker that lost its lease cannot overwrite the new
owner's work. Lock order is room row, then job rows; the claim only *tries* the room lock
(``SKIP LOCKED``), so it never waits in the opposite order.

No function here reads a clock: the caller passes ``now`` (timezone-aware UTC, from the
:class:`app.clock.Clock` it was given), so lease expiry is decided by the caller's clock and
tests can step it.
"""

from __future__ import annotations

import uuid
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, Engine, func, insert, select, update

from app.schemas.statuses import JOB_ACTIVE_STATUSES

from ._calibration_rows import JOB_KIND_CALIBRATION, claimed_job, record_calibration
from ._schema import fingerprints, jobs, matrices, rooms
from .db import translate_errors, write_transaction
from .records import JOB_KIND_BUILD, ClaimedJob, StoredBuild

__all__ = [
    "JOB_KIND_BUILD",
    "JOB_KIND_CALIBRATION",
    "ClaimedJob",
    "JobQueue",
    "StoredBuild",
    "enqueue_build",
    "enqueue_job",
]

_CANDIDATES = 16


def enqueue_build(conn: Connection, *, room_id: str, layout_version: int, now: datetime) -> str:
    """Queue a build of the room's ``layout_version``; returns the job id.

    The caller holds the room row lock. A build job already running for this layout version,
    or any build job still queued for the room (re-pointed at this layout version: it has not
    started, so it simply builds the newest layout), is returned instead of a new one.
    Calibration jobs are never joined: they belong to the layout version they were asked for.
    """
    found = conn.execute(
        select(jobs.c.id, jobs.c.status, jobs.c.layout_version)
        .where(
            jobs.c.room_id == room_id,
            jobs.c.status.in_(JOB_ACTIVE_STATUSES),
            jobs.c.kind == JOB_KIND_BUILD,
        )
        .order_by(jobs.c.created_at.desc(), jobs.c.id.desc())
    ).all()
    for row in found:
        if row.status == "running" and row.layout_version == layout_version:
            return str(row.id)
    for row in found:
        if row.status == "queued":
            conn.execute(
                update(jobs).where(jobs.c.id == row.id).values(layout_version=layout_version)
            )
            conn.execute(update(rooms).where(rooms.c.id == room_id).values(latest_job_id=row.id))
            return str(row.id)
    return enqueue_job(
        conn, room_id=room_id, layout_version=layout_version, kind=JOB_KIND_BUILD, now=now
    )


def enqueue_job(
    conn: Connection, *, room_id: str, layout_version: int, kind: str, now: datetime
) -> str:
    """Insert a new queued job of ``kind`` and make it the room's latest; returns its id.

    The caller holds the room row lock.
    """
    job_id = uuid.uuid4().hex
    conn.execute(
        insert(jobs).values(
            id=job_id,
            kind=kind,
            room_id=room_id,
            status="queued",
            progress=0.0,
            error=None,
            attempts=0,
            layout_version=layout_version,
            created_at=now,
        )
    )
    conn.execute(update(rooms).where(rooms.c.id == room_id).values(latest_job_id=job_id))
    return job_id


def _give_up(
    conn: Connection, job: Any, layout_version: int, max_attempts: int, now: datetime
) -> bool:
    if job.attempts < max_attempts and job.layout_version == layout_version:
        return False
    reason = (
        f"worker lost after {job.attempts} attempt(s) (lease expired)"
        if job.layout_version == layout_version
        else f"superseded: the room's layout is now version {layout_version}"
    )
    conn.execute(
        update(jobs)
        .where(jobs.c.id == job.id)
        .values(status="failed", error=reason, finished_at=now, lease_owner=None)
    )
    return True


def _live_builds(conn: Connection, room_id: str, job_id: str, now: datetime) -> int:
    return int(
        conn.execute(
            select(func.count())
            .select_from(jobs)
            .where(
                jobs.c.room_id == room_id,
                jobs.c.id != job_id,
                jobs.c.status == "running",
                jobs.c.lease_expires_at >= now,
            )
        ).scalar_one()
    )


def _owned(job_id: str, worker_id: str) -> Any:
    return (jobs.c.id == job_id) & (jobs.c.lease_owner == worker_id) & (jobs.c.status == "running")


def _insert_fingerprint(
    conn: Connection, *, claimed: ClaimedJob, build: StoredBuild, version: int, now: datetime
) -> None:
    # A calibration job builds the layout its fit produced; other builds the claimed layout.
    outcome = build.calibration
    conn.execute(
        insert(fingerprints).values(
            room_id=claimed.room_id,
            version=version,
            layout_version=claimed.layout_version,
            layout=claimed.layout if outcome is None else outcome["layout"],
            calibration_id=claimed.calibration_id,
            masked_leds=list(claimed.masked_leds if outcome is None else outcome["masked_leds"]),
            leds=build.leds,
            grid_points=build.grid_points,
            built_at=now,
            build_seconds=build.build_seconds,
            job_id=claimed.job_id,
        )
    )
    for name, (info, size) in build.matrices.items():
        conn.execute(
            insert(matrices).values(
                room_id=claimed.room_id,
                version=version,
                name=name,
                sha256=info.sha256,
                format=info.format,
                shape=list(info.shape),
                size_bytes=size,
            )
        )


class JobQueue:
    """The jobs table as a durable queue: the one door to it (``Registry.jobs``)."""

    def __init__(self, engine: Engine) -> None:
        self._engine = engine

    def claim(
        self,
        *,
        worker_id: str,
        now: datetime,
        lease_seconds: float,
        max_attempts: int,
        max_per_room: int = 1,
        room_id: str | None = None,
    ) -> ClaimedJob | None:
        """Atomically take the oldest claimable job, or None when there is none.

        Claimable: ``queued``, or ``running`` with a lease that expired before ``now``. The claim
        holds until ``now + lease_seconds``. An expired job that already
        used ``max_attempts`` attempts, or whose layout is no longer the room's, is marked
        ``failed`` instead. A room with ``max_per_room`` live builds is skipped. ``room_id``
        restricts the claim to one room's jobs.
        """
        with write_transaction(self._engine) as conn:
            query = select(
                jobs.c.id,
                jobs.c.kind,
                jobs.c.room_id,
                jobs.c.status,
                jobs.c.attempts,
                jobs.c.layout_version,
            ).where(
                (jobs.c.status == "queued")
                | ((jobs.c.status == "running") & (jobs.c.lease_expires_at < now))
            )
            if room_id is not None:
                query = query.where(jobs.c.room_id == room_id)
            candidates = conn.execute(
                query.order_by(jobs.c.created_at, jobs.c.id)
                .limit(_CANDIDATES)
                .with_for_update(skip_locked=True)
            ).all()
            for job in candidates:
                room = conn.execute(
                    select(rooms.c.layout, rooms.c.layout_version)
                    .where(rooms.c.id == job.room_id)
                    .with_for_update(skip_locked=True)
                ).one_or_none()
                if room is None:
                    continue
                # A calibration was asked for one layout version: after a PUT it no longer applies.
                stale = (
                    job.kind == JOB_KIND_CALIBRATION and job.layout_version != room.layout_version
                )
                if (job.status == "running" or stale) and _give_up(
                    conn, job, room.layout_version, max_attempts, now
                ):
                    continue
                if _live_builds(conn, job.room_id, job.id, now) >= max_per_room:
                    continue
                conn.execute(
                    update(jobs)
                    .where(jobs.c.id == job.id)
                    .values(
                        status="running",
                        attempts=job.attempts + 1,
                        progress=0.0,
                        started_at=now,
                        finished_at=None,
                        lease_owner=worker_id,
                        lease_expires_at=now + timedelta(seconds=lease_seconds),
                        heartbeat_at=now,
                        layout_version=room.layout_version,
                    )
                )
                return claimed_job(conn, job=job, room=room, worker_id=worker_id)
        return None

    def heartbeat(
        self, *, job_id: str, worker_id: str, now: datetime, lease_seconds: float
    ) -> bool:
        """Renew the lease until ``now + lease_seconds``; False when the worker no longer owns the
        job (stop reporting).

        A worker whose lease ran out still owns the job until another worker claims it, so a late
        heartbeat of a worker nobody replaced keeps its build.
        """
        with write_transaction(self._engine) as conn:
            result = conn.execute(
                update(jobs)
                .where(_owned(job_id, worker_id))
                .values(heartbeat_at=now, lease_expires_at=now + timedelta(seconds=lease_seconds))
            )
        return bool(result.rowcount)

    def report_progress(self, *, job_id: str, worker_id: str, progress: float) -> bool:
        """Record the build's progress (0..1); False when the worker no longer owns the job."""
        with write_transaction(self._engine) as conn:
            result = conn.execute(
                update(jobs)
                .where(_owned(job_id, worker_id))
                .values(progress=min(max(float(progress), 0.0), 1.0))
            )
        return bool(result.rowcount)

    def complete(self, *, claimed: ClaimedJob, build: StoredBuild, now: datetime) -> int | None:
        """Record the fingerprint and finish the job in one transaction (at ``now``).

        Returns the new fingerprint version, or None when the worker lost the job (lease taken
        over, room deleted) and nothing was recorded. The room's current version switches to the
        new one only when the job's layout version is still the room's and the new version is
        newer than the current one.
        """
        with write_transaction(self._engine) as conn:
            room = conn.execute(
                select(rooms.c.layout_version, rooms.c.current_version)
                .where(rooms.c.id == claimed.room_id)
                .with_for_update()
            ).one_or_none()
            owned = conn.execute(
                select(jobs.c.id).where(_owned(claimed.job_id, claimed.worker_id)).with_for_update()
            ).one_or_none()
            if room is None or owned is None:
                return None
            latest = conn.execute(
                select(func.max(fingerprints.c.version)).where(
                    fingerprints.c.room_id == claimed.room_id
                )
            ).scalar_one()
            version = int(latest or 0) + 1
            _insert_fingerprint(conn, claimed=claimed, build=build, version=version, now=now)
            if claimed.calibration_id is not None and build.calibration is not None:
                record_calibration(
                    conn,
                    calibration_id=claimed.calibration_id,
                    outcome=build.calibration,
                    fingerprint_version=version,
                    now=now,
                )
            conn.execute(
                update(jobs)
                .where(jobs.c.id == claimed.job_id)
                .values(
                    status="succeeded",
                    progress=1.0,
                    error=None,
                    finished_at=now,
                    fingerprint_version=version,
                    lease_owner=None,
                    lease_expires_at=None,
                )
            )
            current = room.current_version
            if claimed.layout_version == room.layout_version and (
                current is None or version > current
            ):
                conn.execute(
                    update(rooms)
                    .where(rooms.c.id == claimed.room_id)
                    .values(current_version=version)
                )
        return version

    def fail(
        self, *, claimed: ClaimedJob, error: str, max_attempts: int, now: datetime
    ) -> str | None:
        """Record a failed attempt: back to ``queued`` while attempts remain, else ``failed``
        (finished at ``now``).

        Returns the new status, or None when the worker no longer owns the job.
        """
        final = claimed.attempts >= max_attempts
        values: dict[str, Any] = {
            "status": "failed" if final else "queued",
            "error": error[:2000],
            "lease_owner": None,
            "lease_expires_at": None,
        }
        if final:
            values["finished_at"] = now
        with translate_errors(), write_transaction(self._engine) as conn:
            result = conn.execute(
                update(jobs).where(_owned(claimed.job_id, claimed.worker_id)).values(**values)
            )
        return str(values["status"]) if result.rowcount else None

    def release(self, *, claimed: ClaimedJob) -> bool:
        """Hand a claimed job back to the queue unfinished (worker shutting down).

        The attempt is not counted. Returns False when the worker no longer owns the job.
        """
        with write_transaction(self._engine) as conn:
            result = conn.execute(
                update(jobs)
                .where(_owned(claimed.job_id, claimed.worker_id))
                .values(
                    status="queued",
                    attempts=max(claimed.attempts - 1, 0),
                    progress=0.0,
                    lease_owner=None,
                    lease_expires_at=None,
                )
            )
        return bool(result.rowcount)
