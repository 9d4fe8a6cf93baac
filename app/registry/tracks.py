"""Tracks of moving terminals: state, bounded history and the per-room event stream.

One update of a room's tracks is one write transaction that first locks the room's
``room_tracking`` row (``SELECT ... FOR UPDATE`` on PostgreSQL; ``BEGIN IMMEDIATE`` on
SQLite), so every API process sees and changes a room's tracks one update at a time: the
caller's ``apply`` reads the tracks as they are and returns what to write
(:class:`~app.registry.records.TrackChanges`); its events are numbered from the room's
sequence in the same transaction. On PostgreSQL the transaction also sends
``NOTIFY vlp_track_events`` with ``room_id:sequence`` (a pointer: listeners read the events
from the table), delivered to every listening process when it commits.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterable
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, Engine, bindparam, delete, func, insert, select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert

from ._rows import decode_cursor, encode_cursor
from ._schema import room_tracking, rooms, track_events, track_points, tracks
from .db import translate_errors, write_transaction
from .errors import InvalidCursor, RegistryUnavailable, RoomNotFound, TrackNotFound
from .records import TrackChanges, TrackEventRecord, TrackPointRecord, TrackRecord

__all__ = ["NOTIFY_CHANNEL", "TrackStore", "new_track_id"]

NOTIFY_CHANNEL = "vlp_track_events"
# How long a listener waits for a notification before looking at ``stop`` again, seconds.
_LISTEN_POLL_S = 0.5

Apply = Callable[[list[TrackRecord], dict[str, Any] | None], TrackChanges]


def new_track_id() -> str:
    """A fresh track id (random: never reused)."""
    return uuid.uuid4().hex


def _track(row: Any) -> TrackRecord:
    return TrackRecord(
        id=str(row.id),
        room_id=str(row.room_id),
        terminal_id=None if row.terminal_id is None else str(row.terminal_id),
        status=str(row.status),
        filter=dict(row.filter),
        x=float(row.x),
        y=float(row.y),
        vx=float(row.vx),
        vy=float(row.vy),
        covariance=[[float(v) for v in line] for line in row.covariance],
        accuracy_m=float(row.accuracy_m),
        state_time=row.state_time,
        created_at=row.created_at,
        updated_at=row.updated_at,
        updates=int(row.updates),
        misses=int(row.misses),
        last_raw=None if row.last_raw is None else dict(row.last_raw),
    )


def _values(record: TrackRecord) -> dict[str, Any]:
    return {
        "id": record.id,
        "room_id": record.room_id,
        "terminal_id": record.terminal_id,
        "status": record.status,
        "filter": record.filter,
        "x": record.x,
        "y": record.y,
        "vx": record.vx,
        "vy": record.vy,
        "covariance": record.covariance,
        "accuracy_m": record.accuracy_m,
        "state_time": record.state_time,
        "created_at": record.created_at,
        "updated_at": record.updated_at,
        "updates": record.updates,
        "misses": record.misses,
        "last_raw": record.last_raw,
    }


def _point(row: Any) -> TrackPointRecord:
    return TrackPointRecord(
        id=int(row.id),
        track_id=str(row.track_id),
        time=row.time,
        x=float(row.x),
        y=float(row.y),
        accuracy_m=float(row.accuracy_m),
        raw_x=None if row.raw_x is None else float(row.raw_x),
        raw_y=None if row.raw_y is None else float(row.raw_y),
        raw_accuracy_m=None if row.raw_accuracy_m is None else float(row.raw_accuracy_m),
    )


class TrackStore:
    """The tracks of every room: the one door to them (``Registry.tracks``)."""

    def __init__(self, engine: Engine) -> None:
        self._engine = engine
        # The stream's reads: one statement each, so on PostgreSQL without a transaction
        # (BEGIN and ROLLBACK would be two more round trips between a commit and its event).
        self._stream_reads = (
            engine.execution_options(isolation_level="AUTOCOMMIT")
            if engine.dialect.name == "postgresql"
            else engine
        )

    # -- updates --------------------------------------------------------------------------
    def update_room(self, *, room_id: str, now: datetime, apply: Apply) -> tuple[TrackChanges, int]:
        """Change a room's tracks atomically: ``apply(tracks, settings)`` sees them all (oldest
        first) under the room's lock and returns the changes, written in the same transaction.

        Returns
        -------
        changes : TrackChanges
            What ``apply`` returned.
        sequence : int
            The room's newest event sequence afterwards.

        Raises
        ------
        RoomNotFound
        """
        with write_transaction(self._engine) as conn:
            state = self._locked_state(conn, room_id)
            rows = conn.execute(
                select(tracks)
                .where(tracks.c.room_id == room_id)
                .order_by(tracks.c.created_at, tracks.c.id)
            ).all()
            loaded = [_track(row) for row in rows]
            changes = apply(loaded, None if state.settings is None else dict(state.settings))
            sequence = self._write(conn, room_id, {t.id for t in loaded}, changes, now, state)
        return changes, sequence

    def _write(
        self,
        conn: Connection,
        room_id: str,
        existing: set[str],
        changes: TrackChanges,
        now: datetime,
        state: Any,
    ) -> int:
        fresh = [_values(t) for t in changes.upserts if t.id not in existing]
        known = [
            {f"b_{k}": v for k, v in _values(t).items()}
            for t in changes.upserts
            if t.id in existing
        ]
        if changes.removed:
            conn.execute(delete(tracks).where(tracks.c.id.in_(changes.removed)))
        if fresh:
            conn.execute(insert(tracks), fresh)
        if known:
            columns = [c.name for c in tracks.c if c.name not in ("id", "room_id", "created_at")]
            conn.execute(
                update(tracks)
                .where(tracks.c.id == bindparam("b_id"))
                .values({name: bindparam(f"b_{name}") for name in columns}),
                known,
            )
        gone = set(changes.removed)
        points = [
            {
                "track_id": p.track_id,
                "room_id": room_id,
                "time": p.time,
                "x": p.x,
                "y": p.y,
                "accuracy_m": p.accuracy_m,
                "raw_x": p.raw_x,
                "raw_y": p.raw_y,
                "raw_accuracy_m": p.raw_accuracy_m,
            }
            for p in changes.points
            if p.track_id not in gone
        ]
        if points:
            conn.execute(insert(track_points), points)
        sequence = int(state.sequence)
        events = []
        for kind, track_id, data in changes.events:
            sequence += 1
            events.append(
                {
                    "room_id": room_id,
                    "sequence": sequence,
                    "kind": kind,
                    "track_id": track_id,
                    "data": data,
                    "created_at": now,
                }
            )
        if events:
            conn.execute(insert(track_events), events)
            advance = (
                update(room_tracking)
                .where(room_tracking.c.room_id == room_id)
                .values(sequence=sequence)
            )
            if conn.dialect.name == "postgresql":
                # Notified by the same statement: one round trip fewer before the commit.
                advance = advance.returning(func.pg_notify(NOTIFY_CHANNEL, f"{room_id}:{sequence}"))
            conn.execute(advance).close()
        if changes.points_before is not None:
            conn.execute(
                delete(track_points).where(
                    track_points.c.room_id == room_id,
                    track_points.c.time < changes.points_before,
                )
            )
        if changes.events_before is not None:
            conn.execute(
                delete(track_events).where(
                    track_events.c.room_id == room_id,
                    track_events.c.created_at < changes.events_before,
                    track_events.c.sequence < sequence,  # the newest always stays
                )
            )
        return sequence

    def _locked_state(self, conn: Connection, room_id: str) -> Any:
        """The room's ``room_tracking`` row (sequence, settings), locked until ``conn``
        commits; made first when the room has none yet (RoomNotFound).

        Made in the update's own transaction, and only when missing: every statement is a
        round trip to the database, and an update is on the way from a POST to its event."""
        locked = (
            select(room_tracking.c.sequence, room_tracking.c.settings)
            .where(room_tracking.c.room_id == room_id)
            .with_for_update()
        )
        state = conn.execute(locked).one_or_none()
        if state is None:
            self._insert_row(conn, room_id)
            state = conn.execute(locked).one()
        return state

    @staticmethod
    def _insert_row(conn: Connection, room_id: str) -> None:
        """Make the room's ``room_tracking`` row unless it exists (RoomNotFound)."""
        if conn.execute(select(rooms.c.id).where(rooms.c.id == room_id)).first() is None:
            raise RoomNotFound(f"no room with id {room_id!r}", field="room_id")
        maker = pg_insert if conn.dialect.name == "postgresql" else sqlite_insert
        conn.execute(
            maker(room_tracking)
            .values(room_id=room_id, sequence=0, settings=None)
            .on_conflict_do_nothing(index_elements=["room_id"])
        )

    def put_settings(self, *, room_id: str, settings: dict[str, Any] | None) -> None:
        """Store a room's tracking settings (None: the defaults). RoomNotFound."""
        with write_transaction(self._engine) as conn:
            self._insert_row(conn, room_id)
            conn.execute(
                update(room_tracking)
                .where(room_tracking.c.room_id == room_id)
                .values(settings=settings)
            )

    def get_settings(self, *, room_id: str) -> dict[str, Any] | None:
        """A room's stored tracking settings (None: the defaults)."""
        with translate_errors(), self._engine.connect() as conn:
            value = conn.execute(
                select(room_tracking.c.settings).where(room_tracking.c.room_id == room_id)
            ).scalar_one_or_none()
        return None if value is None else dict(value)

    # -- reads ----------------------------------------------------------------------------
    def list_tracks(
        self, *, room_id: str, statuses: Iterable[str], limit: int, cursor: str | None
    ) -> tuple[list[TrackRecord], str | None]:
        """A room's tracks with one of ``statuses``, oldest first, ``limit`` at a time."""
        query = (
            select(tracks)
            .where(tracks.c.room_id == room_id, tracks.c.status.in_(list(statuses)))
            .order_by(tracks.c.created_at, tracks.c.id)
            .limit(limit + 1)
        )
        if cursor is not None:
            created_at, track_id = decode_cursor(cursor)
            query = query.where(
                (tracks.c.created_at > created_at)
                | ((tracks.c.created_at == created_at) & (tracks.c.id > track_id))
            )
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(query).all()
        records = [_track(row) for row in rows[:limit]]
        if len(rows) <= limit or not records:
            return records, None
        return records, encode_cursor(records[-1].created_at, records[-1].id)

    def all_tracks(self, *, room_id: str) -> list[TrackRecord]:
        """Every track of a room, oldest first."""
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(
                select(tracks)
                .where(tracks.c.room_id == room_id)
                .order_by(tracks.c.created_at, tracks.c.id)
            ).all()
        return [_track(row) for row in rows]

    def get_track(self, *, room_id: str, track_id: str) -> TrackRecord:
        """One track of a room; :class:`TrackNotFound` when unknown or ended."""
        with translate_errors(), self._engine.connect() as conn:
            row = conn.execute(
                select(tracks).where(tracks.c.id == track_id, tracks.c.room_id == room_id)
            ).one_or_none()
        if row is None:
            raise TrackNotFound(f"room {room_id} has no track {track_id!r}", field="track_id")
        return _track(row)

    def list_points(
        self,
        *,
        room_id: str,
        track_id: str,
        since: datetime | None,
        limit: int,
        cursor: str | None,
    ) -> tuple[list[TrackPointRecord], str | None]:
        """A track's points in the order they were stored, from ``since`` on (TrackNotFound)."""
        self.get_track(room_id=room_id, track_id=track_id)
        query = (
            select(track_points)
            .where(track_points.c.track_id == track_id)
            .order_by(track_points.c.id)
            .limit(limit + 1)
        )
        if since is not None:
            query = query.where(track_points.c.time >= since)
        if cursor is not None:
            if not cursor.isdigit() or len(cursor) > 19:
                raise InvalidCursor(f"invalid cursor {cursor!r}", field="cursor")
            query = query.where(track_points.c.id > int(cursor))
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(query).all()
        points = [_point(row) for row in rows[:limit]]
        if len(rows) <= limit or not points:
            return points, None
        return points, str(points[-1].id)

    def events_since(self, *, room_id: str, after: int, limit: int) -> list[TrackEventRecord]:
        """The room's kept events with a sequence above ``after``, in order."""
        with translate_errors(), self._stream_reads.connect() as conn:
            rows = conn.execute(
                select(track_events)
                .where(track_events.c.room_id == room_id, track_events.c.sequence > after)
                .order_by(track_events.c.sequence)
                .limit(limit)
            ).all()
        return [
            TrackEventRecord(
                room_id=str(row.room_id),
                sequence=int(row.sequence),
                kind=str(row.kind),
                track_id=str(row.track_id),
                data=dict(row.data),
                created_at=row.created_at,
            )
            for row in rows
        ]

    def latest_sequence(self, *, room_id: str) -> int:
        """The room's newest event sequence (0 before its first event)."""
        with translate_errors(), self._engine.connect() as conn:
            value = conn.execute(
                select(room_tracking.c.sequence).where(room_tracking.c.room_id == room_id)
            ).scalar_one_or_none()
        return 0 if value is None else int(value)

    def rooms_with_tracks(self) -> list[str]:
        """Rooms that have at least one track."""
        with translate_errors(), self._engine.connect() as conn:
            rows = conn.execute(select(tracks.c.room_id).distinct()).all()
        return [str(row.room_id) for row in rows]

    def count_points(self, *, room_id: str) -> int:
        """How many history points a room keeps."""
        with translate_errors(), self._engine.connect() as conn:
            return int(
                conn.execute(
                    select(func.count())
                    .select_from(track_points)
                    .where(track_points.c.room_id == room_id)
                ).scalar_one()
            )

    # -- notifications --------------------------------------------------------------------
    @property
    def notifies(self) -> bool:
        """Whether committed events are announced to listeners (PostgreSQL)."""
        return self._engine.dialect.name == "postgresql"

    def listen(self, on_event: Callable[[str, int], None], stop: threading.Event) -> None:
        """Call ``on_event(room_id, sequence)`` for every event any process commits, until
        ``stop`` is set (PostgreSQL ``LISTEN``; returns at once on other backends).

        Raises
        ------
        RegistryUnavailable
            When the connection is lost; the caller listens again.
        """
        if not self.notifies:
            return
        import psycopg  # PostgreSQL's driver: loaded only where notifications are listened to

        raw = self._engine.raw_connection()
        try:
            connection: Any = raw.driver_connection
            connection.autocommit = True
            connection.execute(f"LISTEN {NOTIFY_CHANNEL}")
            while not stop.is_set():
                for notice in connection.notifies(timeout=_LISTEN_POLL_S):
                    room_id, _, sequence = str(notice.payload).rpartition(":")
                    if sequence.isdigit():
                        on_event(room_id, int(sequence))
                    if stop.is_set():
                        break
        except psycopg.Error as exc:
            raise RegistryUnavailable("the registry's notification connection was lost") from exc
        finally:
            raw.invalidate()  # never return a LISTENing connection to the pool
