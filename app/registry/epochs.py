"""Cooperation epochs: a short window that terminals join one by one, solved exactly once.

Life of an epoch: ``open`` (terminals post; a post again with the same ``terminal_id``
replaces its row) -> ``solving`` (claimed) -> ``solved`` | ``expired`` | ``failed``.

Exactly-once across API processes: the step ``open -> solving`` is one conditional
``UPDATE`` (:func:`claim_epoch`); only the process whose update changed the row solves, and
it writes the result guarded by its ``claim_owner`` (:func:`finish_epoch`), so a solver that
lost its claim cannot overwrite a newer one. A claim is a lease: a process that dies while
solving leaves ``solving`` with a ``claim_expires_at`` in the past, and the epoch is
claimable again (``attempts`` counts claims; after ``max_attempts`` it becomes ``failed``).

Posts lock the epoch row (``SELECT ... FOR UPDATE`` on PostgreSQL, ``BEGIN IMMEDIATE`` on
SQLite) and check that it is open in that transaction, so a claim waits for a post in flight
and the solver always reads every accepted post.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, Engine, and_, delete, func, insert, or_, select, update

from app.schemas.statuses import EPOCH_FINAL_STATUSES

from ._schema import epoch_measurements, epochs
from .db import translate_errors, write_transaction
from .errors import EpochClosed, EpochFull, EpochNotFound
from .records import ClaimedEpoch, EpochRecord, EpochSettings

__all__ = ["EpochStore"]


def _terminal_count() -> Any:
    return (
        select(func.count())
        .select_from(epoch_measurements)
        .where(epoch_measurements.c.epoch_id == epochs.c.id)
        .scalar_subquery()
        .label("terminal_count")
    )


def _record(row: Any) -> EpochRecord:
    return EpochRecord(
        id=str(row.id),
        room_id=str(row.room_id),
        status=str(row.status),
        settings=EpochSettings(
            model=str(row.model),
            solver=str(row.solver),
            targets=None if row.targets is None else int(row.targets),
            min_terminals=int(row.min_terminals),
            max_terminals=int(row.max_terminals),
            window_s=float(row.window_s),
            fingerprint_version=int(row.fingerprint_version),
            leds=int(row.leds),
            track=bool(row.track),
        ),
        terminals=int(row.terminal_count),
        created_at=row.created_at,
        expires_at=row.expires_at,
        finished_at=row.finished_at,
        attempts=int(row.attempts),
        localization=None if row.localization is None else dict(row.localization),
        error=None if row.error is None else str(row.error),
    )


def _read(conn: Connection, *, room_id: str, epoch_id: str) -> EpochRecord:
    row = conn.execute(
        select(epochs, _terminal_count()).where(
            epochs.c.id == epoch_id, epochs.c.room_id == room_id
        )
    ).one_or_none()
    if row is None:
        raise EpochNotFound(f"room {room_id} has no epoch {epoch_id!r}", field="epoch_id")
    return _record(row)


def _closed_reason(row: Any, now: datetime) -> str | None:
    if row.status != "open":
        return f"epoch {row.id} is {row.status}; posts are taken only while it is open"
    if row.expires_at <= now:
        return f"the window of epoch {row.id} closed at {row.expires_at.isoformat()}"
    return None


def _upsert(conn: Connection, epoch: Any, terminal_id: str, values: dict[str, Any]) -> None:
    # Replace the terminal's row, else add one if the epoch has room. The caller holds the
    # epoch row lock, so no other post of this epoch runs between the update and the insert.
    mine = (epoch_measurements.c.epoch_id == epoch.id) & (
        epoch_measurements.c.terminal_id == terminal_id
    )
    if conn.execute(update(epoch_measurements).where(mine).values(**values)).rowcount:
        return
    count = conn.execute(
        select(func.count())
        .select_from(epoch_measurements)
        .where(epoch_measurements.c.epoch_id == epoch.id)
    ).scalar_one()
    if count >= epoch.max_terminals:
        raise EpochFull(
            f"epoch {epoch.id} already has its maximum of {epoch.max_terminals} terminals"
        )
    conn.execute(
        insert(epoch_measurements).values(epoch_id=epoch.id, terminal_id=terminal_id, **values)
    )


def _claimed(conn: Connection, record: EpochRecord, owner: str) -> ClaimedEpoch:
    rows = conn.execute(
        select(
            epoch_measurements.c.terminal_id,
            epoch_measurements.c.amplitudes,
            epoch_measurements.c.detection_floor,
        )
        .where(epoch_measurements.c.epoch_id == record.id)
        .order_by(epoch_measurements.c.posted_at, epoch_measurements.c.terminal_id)
    ).all()
    return ClaimedEpoch(
        record=record,
        owner=owner,
        terminal_ids=tuple(str(row.terminal_id) for row in rows),
        amplitudes=tuple(
            tuple(None if a is None else float(a) for a in row.amplitudes) for row in rows
        ),
        detection_floors=tuple(
            None if row.detection_floor is None else float(row.detection_floor) for row in rows
        ),
    )


class EpochStore:
    """The epochs and their posts: the one door to them (``Registry.epochs``)."""

    def __init__(self, engine: Engine) -> None:
        self._engine = engine

    def create(self, *, room_id: str, settings: EpochSettings, now: datetime) -> EpochRecord:
        """Open a new epoch of a room (the caller checked the room and its fingerprint)."""
        epoch_id = uuid.uuid4().hex
        with write_transaction(self._engine) as conn:
            conn.execute(
                insert(epochs).values(
                    id=epoch_id,
                    room_id=room_id,
                    status="open",
                    model=settings.model,
                    solver=settings.solver,
                    targets=settings.targets,
                    min_terminals=settings.min_terminals,
                    max_terminals=settings.max_terminals,
                    window_s=settings.window_s,
                    fingerprint_version=settings.fingerprint_version,
                    leds=settings.leds,
                    track=settings.track,
                    created_at=now,
                    expires_at=now + timedelta(seconds=settings.window_s),
                    attempts=0,
                )
            )
            return _read(conn, room_id=room_id, epoch_id=epoch_id)

    def get(self, *, room_id: str, epoch_id: str) -> EpochRecord:
        """One epoch of a room; :class:`EpochNotFound` when unknown."""
        with translate_errors(), self._engine.connect() as conn:
            return _read(conn, room_id=room_id, epoch_id=epoch_id)

    def post_measurement(
        self,
        *,
        room_id: str,
        epoch_id: str,
        terminal_id: str,
        amplitudes: Sequence[float | None],
        now: datetime,
        detection_floor: float | None = None,
    ) -> EpochRecord:
        """Store (or replace) one terminal's amplitudes (None: an LED it did not detect,
        stored as JSON null) and its own detection floor while the epoch is open.

        Raises
        ------
        EpochNotFound
        EpochClosed
            The epoch is not open or its window has passed.
        EpochFull
            A new terminal when ``max_terminals`` have posted already.
        ValueError
            Not one amplitude per LED of the epoch's fingerprint (the caller fits a
            terminal's values to the fingerprint first, see
            :func:`app.services.masking.fit_to_fingerprint`).
        """
        with write_transaction(self._engine) as conn:
            row = conn.execute(
                select(epochs)
                .where(epochs.c.id == epoch_id, epochs.c.room_id == room_id)
                .with_for_update()
            ).one_or_none()
            if row is None:
                raise EpochNotFound(f"room {room_id} has no epoch {epoch_id!r}", field="epoch_id")
            reason = _closed_reason(row, now)
            if reason is not None:
                raise EpochClosed(reason)
            if len(amplitudes) != row.leds:
                raise ValueError(
                    f"expected {row.leds} amplitudes (the epoch's fingerprint LEDs), "
                    f"got {len(amplitudes)}: fit them to the fingerprint before posting"
                )
            values = {
                "amplitudes": [None if a is None else float(a) for a in amplitudes],
                "detection_floor": None if detection_floor is None else float(detection_floor),
                "posted_at": now,
            }
            _upsert(conn, row, terminal_id, values)
            return _read(conn, room_id=room_id, epoch_id=epoch_id)

    def claim(
        self,
        *,
        room_id: str,
        epoch_id: str,
        owner: str,
        now: datetime,
        lease_s: float,
        max_attempts: int,
        force: bool,
    ) -> ClaimedEpoch | None:
        """Take the epoch for solving, or None when it is not this caller's to solve.

        Claimable: ``open`` with its window passed (or any ``open`` one when ``force``, i.e. an
        explicit ``solve``), or ``solving`` with an expired claim and fewer than ``max_attempts``
        claims so far (one that used them all is marked ``failed`` here instead).
        """
        lease_over = (epochs.c.status == "solving") & (epochs.c.claim_expires_at <= now)
        mine = (epochs.c.id == epoch_id) & (epochs.c.room_id == room_id)
        with write_transaction(self._engine) as conn:
            # Lost too often: give up rather than crash every process that picks it up.
            conn.execute(
                update(epochs)
                .where(mine, lease_over, epochs.c.attempts >= max_attempts)
                .values(
                    status="failed",
                    error=f"the solve was lost {max_attempts} times (solver process gone)",
                    finished_at=now,
                    claim_owner=None,
                )
            )
            openable = epochs.c.status == "open"
            if not force:
                openable = and_(openable, epochs.c.expires_at <= now)
            claimed = conn.execute(
                update(epochs)
                .where(mine, or_(openable, lease_over))
                .values(
                    status="solving",
                    claim_owner=owner,
                    claim_expires_at=now + timedelta(seconds=lease_s),
                    attempts=epochs.c.attempts + 1,
                )
            ).rowcount
            if claimed != 1:
                return None
            return _claimed(conn, _read(conn, room_id=room_id, epoch_id=epoch_id), owner)

    def finish(
        self,
        *,
        claimed: ClaimedEpoch,
        status: str,
        now: datetime,
        localization: dict[str, Any] | None = None,
        error: str | None = None,
    ) -> bool:
        """Record the outcome of a claimed epoch; False when the claim was lost meanwhile."""
        if status not in EPOCH_FINAL_STATUSES:
            raise ValueError(f"an epoch finishes as one of {EPOCH_FINAL_STATUSES}, not {status!r}")
        with write_transaction(self._engine) as conn:
            changed = conn.execute(
                update(epochs)
                .where(
                    epochs.c.id == claimed.record.id,
                    epochs.c.status == "solving",
                    epochs.c.claim_owner == claimed.owner,
                )
                .values(
                    status=status,
                    localization=localization,
                    error=error,
                    finished_at=now,
                    claim_owner=None,
                    claim_expires_at=None,
                )
            ).rowcount
        return bool(changed == 1)

    def due(self, *, now: datetime, limit: int) -> list[tuple[str, str]]:
        """``(room_id, epoch_id)`` of epochs to settle now: open past their window, or solving
        with an expired claim; oldest deadline first."""
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(
                select(epochs.c.room_id, epochs.c.id)
                .where(
                    ((epochs.c.status == "open") & (epochs.c.expires_at <= now))
                    | ((epochs.c.status == "solving") & (epochs.c.claim_expires_at <= now))
                )
                .order_by(epochs.c.expires_at, epochs.c.id)
                .limit(limit)
            ).all()
        return [(str(row.room_id), str(row.id)) for row in rows]

    def purge(self, *, finished_before: datetime) -> int:
        """Delete finished epochs (and their posts) older than ``finished_before``; how many."""
        with write_transaction(self._engine) as conn:
            return int(
                conn.execute(
                    delete(epochs).where(
                        epochs.c.status.in_(EPOCH_FINAL_STATUSES),
                        epochs.c.finished_at < finished_before,
                    )
                ).rowcount
            )
