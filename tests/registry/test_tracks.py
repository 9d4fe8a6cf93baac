"""The track store on SQLite and PostgreSQL: atomic per-room updates, numbered events,
bounded history, notifications."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from sqlalchemy import Engine, event

from app.registry import Registry
from app.registry.errors import RoomNotFound, TrackNotFound
from app.registry.records import TrackChanges, TrackPointRecord, TrackRecord
from app.registry.tracks import new_track_id
from tests.db_fixtures import raw_engine, small_layout

T0 = datetime(2026, 1, 1, 12, 0, tzinfo=UTC)


def _track(room_id: str, *, terminal_id: str | None = None, when: datetime = T0) -> TrackRecord:
    return TrackRecord(
        id=new_track_id(),
        room_id=room_id,
        terminal_id=terminal_id,
        status="tentative",
        filter={"means": [], "covariances": [], "model_probabilities": [], "wild": 0},
        x=1.0,
        y=2.0,
        vx=0.0,
        vy=0.0,
        covariance=[[1e-4, 0.0], [0.0, 1e-4]],
        accuracy_m=0.02,
        state_time=when,
        created_at=when,
        updated_at=when,
        updates=1,
        misses=0,
        last_raw=None,
    )


def _add_one(room_id: str, seen: list[int]) -> Any:
    """An ``apply`` that records how many tracks it saw and adds one (with its event)."""

    def apply(records: list[TrackRecord], settings: dict[str, Any] | None) -> TrackChanges:
        del settings
        seen.append(len(records))
        track = _track(room_id)
        return TrackChanges(upserts=(track,), events=(("track", track.id, {"id": track.id}),))

    return apply


@contextmanager
def _sent(engine: Engine) -> Iterator[list[tuple[str, bool]]]:
    """What the registry sends to the database meanwhile: ``("BEGIN", False)`` per
    transaction, and each statement's first words with whether its connection was in
    autocommit (PostgreSQL's driver; False on SQLite)."""
    sent: list[tuple[str, bool]] = []

    def on_begin(conn: Any) -> None:
        del conn
        sent.append(("BEGIN", False))

    def on_execute(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        del cursor
        autocommit = bool(getattr(conn.connection.driver_connection, "autocommit", False))
        sent.append((" ".join(statement.split()[:3]), autocommit))

    event.listen(engine, "begin", on_begin)
    event.listen(engine, "before_cursor_execute", on_execute)
    try:
        yield sent
    finally:
        event.remove(engine, "before_cursor_execute", on_execute)
        event.remove(engine, "begin", on_begin)


def test_an_update_is_one_transaction(registry: Registry) -> None:
    """Each round trip to the database is on the way from a POST to its event: an update is
    one transaction, and the room's tracking row is made in it only the first time."""
    room = registry.create_room(name="r", layout=small_layout())
    engine = raw_engine(registry)
    with _sent(engine) as first:
        registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, []))
    assert [text for text, _ in first].count("BEGIN") == 1
    assert any(text.startswith("INSERT INTO room_tracking") for text, _ in first)
    with _sent(engine) as later:
        registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, []))
    assert [text for text, _ in later].count("BEGIN") == 1
    assert not any("room_tracking" in text and text.startswith("INSERT") for text, _ in later)
    assert registry.tracks.latest_sequence(room_id=room.id) == 2


def test_settings_before_the_first_update_are_kept(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    registry.tracks.put_settings(room_id=room.id, settings={"lost_after_s": 9.0})
    stored: list[dict[str, Any] | None] = []

    def apply(records: list[TrackRecord], settings: dict[str, Any] | None) -> TrackChanges:
        del records
        stored.append(settings)
        return TrackChanges()

    registry.tracks.update_room(room_id=room.id, now=T0, apply=apply)
    assert stored == [{"lost_after_s": 9.0}]
    with pytest.raises(RoomNotFound):
        registry.tracks.put_settings(room_id="nope", settings=None)


def test_the_stream_read_is_one_statement_without_a_transaction(registry: Registry) -> None:
    """On PostgreSQL the stream's read of new events runs in autocommit: no BEGIN and no
    ROLLBACK round trips between a commit and its event reaching a reader."""
    room = registry.create_room(name="r", layout=small_layout())
    registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, []))
    with _sent(raw_engine(registry)) as sent:
        events = registry.tracks.events_since(room_id=room.id, after=0, limit=10)
    assert [e.sequence for e in events] == [1]
    statements = [(text, autocommit) for text, autocommit in sent if text != "BEGIN"]
    assert len(statements) == 1 and statements[0][0].startswith("SELECT")
    assert statements[0][1] == registry.tracks.notifies  # autocommit on PostgreSQL


def test_updates_number_events_and_keep_tracks(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    seen: list[int] = []
    for _ in range(3):
        registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, seen))
    assert seen == [0, 1, 2]
    assert registry.tracks.latest_sequence(room_id=room.id) == 3
    events = registry.tracks.events_since(room_id=room.id, after=1, limit=10)
    assert [e.sequence for e in events] == [2, 3]
    tracks, cursor = registry.tracks.list_tracks(
        room_id=room.id, statuses=["tentative"], limit=2, cursor=None
    )
    assert len(tracks) == 2 and cursor is not None
    rest, last = registry.tracks.list_tracks(
        room_id=room.id, statuses=["tentative"], limit=2, cursor=cursor
    )
    assert len(rest) == 1 and last is None
    every = registry.tracks.events_since(room_id=room.id, after=0, limit=10)
    assert {t.id for t in tracks + rest} == {e.track_id for e in every}


def test_concurrent_updates_of_one_room_are_serialised(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    seen: list[int] = []
    barrier = threading.Barrier(6)
    errors: list[BaseException] = []

    def writer() -> None:
        barrier.wait()
        try:
            for _ in range(5):
                registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, seen))
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=writer) for _ in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not errors
    # Each update saw every earlier one: no two read the same state.
    assert sorted(seen) == list(range(30))
    assert registry.tracks.latest_sequence(room_id=room.id) == 30
    sequences = [
        e.sequence for e in registry.tracks.events_since(room_id=room.id, after=0, limit=100)
    ]
    assert sequences == list(range(1, 31))


def test_history_is_bounded_and_the_newest_event_stays(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    track = _track(room.id)

    def first(records: list[TrackRecord], settings: dict[str, Any] | None) -> TrackChanges:
        del records, settings
        points = tuple(
            TrackPointRecord(
                track_id=track.id, time=T0 + timedelta(seconds=s), x=1.0, y=2.0, accuracy_m=0.1
            )
            for s in range(10)
        )
        return TrackChanges(
            upserts=(track,), points=points, events=(("track", track.id, {"id": track.id}),)
        )

    registry.tracks.update_room(room_id=room.id, now=T0, apply=first)

    def later(records: list[TrackRecord], settings: dict[str, Any] | None) -> TrackChanges:
        del records, settings
        return TrackChanges(
            events=(("track", track.id, {"id": track.id}),),
            points_before=T0 + timedelta(seconds=6),
            events_before=T0 + timedelta(hours=1),
        )

    registry.tracks.update_room(room_id=room.id, now=T0 + timedelta(seconds=5), apply=later)
    points, _ = registry.tracks.list_points(
        room_id=room.id, track_id=track.id, since=None, limit=100, cursor=None
    )
    assert [p.time for p in points] == [T0 + timedelta(seconds=s) for s in range(6, 10)]
    events = registry.tracks.events_since(room_id=room.id, after=0, limit=10)
    assert [e.sequence for e in events] == [2]  # older ones pruned, the newest kept


def test_unknown_rooms_and_tracks(registry: Registry) -> None:
    with pytest.raises(RoomNotFound):
        registry.tracks.update_room(room_id="nope", now=T0, apply=_add_one("nope", []))
    room = registry.create_room(name="r", layout=small_layout())
    with pytest.raises(TrackNotFound):
        registry.tracks.get_track(room_id=room.id, track_id="nope")
    registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, []))
    assert registry.tracks.rooms_with_tracks() == [room.id]
    registry.delete_room(room_id=room.id)
    assert registry.tracks.rooms_with_tracks() == []
    assert registry.tracks.events_since(room_id=room.id, after=0, limit=10) == []


def test_settings_are_stored_per_room(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    assert registry.tracks.get_settings(room_id=room.id) is None
    registry.tracks.put_settings(room_id=room.id, settings={"lost_after_s": 9.0})
    assert registry.tracks.get_settings(room_id=room.id) == {"lost_after_s": 9.0}


def test_commits_are_announced_to_listeners(registry: Registry) -> None:
    room = registry.create_room(name="r", layout=small_layout())
    if not registry.tracks.notifies:  # SQLite: readers poll; nothing to listen to
        stop = threading.Event()
        registry.tracks.listen(lambda *_: None, stop)  # returns at once
        return
    heard: list[tuple[str, int]] = []
    arrived = threading.Event()
    stop = threading.Event()

    def on_event(room_id: str, sequence: int) -> None:
        heard.append((room_id, sequence))
        arrived.set()

    listener = threading.Thread(target=registry.tracks.listen, args=(on_event, stop))
    listener.start()
    try:
        # The listener may subscribe after a first commit: commit until one is heard.
        for _ in range(50):
            registry.tracks.update_room(room_id=room.id, now=T0, apply=_add_one(room.id, []))
            if arrived.wait(timeout=1.0):
                break
    finally:
        stop.set()
        listener.join(timeout=30)
    assert heard and heard[0][0] == room.id
    assert heard[0][1] >= 1
