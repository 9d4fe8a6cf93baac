"""Tracking: a localization's estimates update the room's tracks; tracks age and end.

:meth:`Tracking.track` is what a localize request with ``track: true`` (and a solved epoch)
calls after solving: under the room's lock (:meth:`app.registry.tracks.TrackStore.update_room`)
the estimates with a ``terminal_id`` update that terminal's track and the others are
associated with the room's anonymous tracks (:mod:`app.vlp.tracking`); the answer's estimates
get ``track_id`` and ``tracked``. Every change is an event of the room's stream; after the
commit ``on_event(room_id, sequence)`` tells this process's stream readers (other processes
hear it through the registry's notifications, see :mod:`app.services.track_stream`).
:meth:`Tracking.sweep` marks tracks lost and ends them as time passes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

import numpy as np

from app.clock import Clock
from app.errors import InvalidFields, RecordNotFound, TrackNotFound
from app.registry import Registry
from app.registry.records import TrackChanges, TrackPointRecord, TrackRecord
from app.registry.tracks import new_track_id
from app.schemas import (
    Estimate,
    Localization,
)
from app.vlp.radii import confidence_radii
from app.vlp.tracking import (
    STATUS_NAMES,
    TrackerSettings,
    Tracks,
    age_tracks,
    estimates,
    joined,
    step_anonymous,
    step_labelled,
)
from app.vlp.typing import FloatArray, IntArray

from ._track_state import (
    filter_json,
    rival_json,
    seconds,
    to_time,
    track_public,
    tracked_state,
    tracker_settings,
    tracks_of,
)

__all__ = ["MAX_FUTURE_S", "Tracking"]

# A measurement's time may run ahead of the service's clock by this much (terminals' clocks).
MAX_FUTURE_S = 60.0
# A room's points and events older than its history_s are deleted by at most one update in
# each tenth of history_s, not by every update: the two deletes are round trips inside the
# update's transaction, on the way from a POST to its event. History is kept for history_s
# and at most a tenth longer.
PRUNES_PER_HISTORY = 10


@dataclass
class _Fixes:
    """The estimates of one answer as arrays, split into labelled and anonymous."""

    positions: FloatArray
    covariances: FloatArray
    radii: FloatArray
    terminal_ids: list[str | None]

    @property
    def labelled(self) -> IntArray:
        return np.array([i for i, t in enumerate(self.terminal_ids) if t], dtype=np.intp)

    @property
    def anonymous(self) -> IntArray:
        return np.array([i for i, t in enumerate(self.terminal_ids) if not t], dtype=np.intp)


@dataclass
class _Outcome:
    """What the update under the lock decided for each estimate."""

    records: dict[str, TrackRecord] = field(default_factory=dict)
    estimate_tracks: list[str] = field(default_factory=list)


class Tracking:
    """The rooms' tracks of one API process; thread-safe (state lives in the registry).

    Parameters
    ----------
    registry : Registry
    clock : Clock
        What "now" is for ``updated_at``, the ageing of tracks and the history kept.
    on_event : callable, default=None
        ``on_event(room_id, sequence)`` after a commit that added events.
    """

    def __init__(
        self,
        *,
        registry: Registry,
        clock: Clock,
        on_event: Callable[[str, int], None] | None = None,
    ) -> None:
        self._registry = registry
        self._clock = clock
        self._on_event = on_event
        # When this process last pruned each room's history (other processes prune too).
        self._pruned: dict[str, datetime] = {}

    # -- updates --------------------------------------------------------------------------
    def track(
        self, *, room_id: str, localization: Localization, time: datetime | None
    ) -> Localization:
        """Update the room's tracks with the answer's estimates (measured at ``time``, else
        now); the answer with ``track_id`` and ``tracked`` on every estimate.

        Raises
        ------
        InvalidFields
            ``time`` more than :data:`MAX_FUTURE_S` ahead of the service's clock.
        RoomNotFound
        """
        now = self._clock.now()
        when = now if time is None else time
        if (when - now).total_seconds() > MAX_FUTURE_S:
            raise InvalidFields(
                [
                    (
                        "time",
                        f"time {when.isoformat()} is more than {MAX_FUTURE_S:g} s after the "
                        f"service's clock ({now.isoformat()})",
                    )
                ]
            )
        fixes = self._fixes(room_id, localization.estimates)
        outcome = _Outcome()

        def apply(records: list[TrackRecord], stored: dict[str, Any] | None) -> TrackChanges:
            return self._apply(room_id, records, tracker_settings(stored), fixes, when, outcome)

        _, sequence = self._registry.tracks.update_room(room_id=room_id, now=now, apply=apply)
        self._announce(room_id, sequence)
        estimates = [
            estimate.model_copy(
                update={"track_id": track_id, "tracked": tracked_state(outcome.records[track_id])}
            )
            for estimate, track_id in zip(
                localization.estimates, outcome.estimate_tracks, strict=True
            )
        ]
        return localization.model_copy(update={"estimates": estimates})

    def _fixes(self, room_id: str, estimates: list[Estimate]) -> _Fixes:
        """The estimates' positions and covariances; an estimate without a covariance (grid
        solvers) counts as a square of the grid's step."""
        fallback = None
        covariances = []
        for estimate in estimates:
            if estimate.covariance is not None:
                covariances.append(np.array(estimate.covariance, dtype=np.float64))
                continue
            if fallback is None:
                step = float(self._registry.get_room(room_id=room_id).layout["grid"]["step"])
                fallback = np.eye(2) * step**2
            covariances.append(fallback)
        cov = np.array(covariances).reshape(-1, 2, 2)
        return _Fixes(
            positions=np.array([[e.x, e.y] for e in estimates], dtype=np.float64).reshape(-1, 2),
            covariances=cov,
            radii=confidence_radii(cov),
            terminal_ids=[e.terminal_id for e in estimates],
        )

    def _apply(
        self,
        room_id: str,
        records: list[TrackRecord],
        settings: TrackerSettings,
        fixes: _Fixes,
        when: datetime,
        outcome: _Outcome,
    ) -> TrackChanges:
        """Under the room's lock: the fixes applied to the stored tracks, as changes."""
        time_s = seconds(when)
        tracks = tracks_of(records)
        terminals: list[str | None] = [r.terminal_id for r in records]
        fix_rows = np.zeros(len(fixes.terminal_ids), dtype=np.intp)
        labelled, anonymous = fixes.labelled, fixes.anonymous
        if labelled.size:
            owner = {t: row for row, t in enumerate(terminals) if t}
            rows = np.array([owner.get(fixes.terminal_ids[i], -1) for i in labelled], np.intp)
            step = step_labelled(
                tracks,
                rows,
                fixes.positions[labelled],
                fixes.covariances[labelled],
                time_s,
                settings,
            )
            tracks, fix_rows[labelled] = step.tracks, step.fix_rows
            terminals += [fixes.terminal_ids[i] for i in labelled[rows < 0]]
        if anonymous.size:
            mine = np.array([row for row, t in enumerate(terminals) if t is None], np.intp)
            step = step_anonymous(
                _take(tracks, mine),
                fixes.positions[anonymous],
                fixes.covariances[anonymous],
                time_s,
                settings,
            )
            before = tracks.size
            tracks = _merge(tracks, mine, step.tracks)
            rows_of = np.concatenate((mine, before + np.arange(tracks.size - before)))
            fix_rows[anonymous] = rows_of[step.fix_rows]
            terminals += [None] * (tracks.size - before)
        ids = [r.id for r in records] + [new_track_id() for _ in range(tracks.size - len(records))]
        status, removed = age_tracks(tracks, time_s, settings)
        tracks = dataclasses.replace(tracks, status=status)
        changed = np.zeros(tracks.size, dtype=bool)
        changed[fix_rows] = True
        changed[len(records) :] = True
        for row, record in enumerate(records):
            changed[row] |= (STATUS_NAMES[status[row]], int(tracks.misses[row])) != (
                record.status,
                record.misses,
            )
        written = self._records(room_id, records, ids, terminals, tracks, changed & ~removed)
        for k, row in enumerate(fix_rows.tolist()):
            if ids[row] in written:
                written[ids[row]] = _with_raw(written[ids[row]], fixes, k)
        outcome.records.update(written)
        for record in records:
            outcome.records.setdefault(record.id, record)
        outcome.estimate_tracks[:] = [ids[row] for row in fix_rows]
        return self._changes(
            room_id, records, ids, written, removed, fixes, fix_rows, when, settings
        )

    def _records(
        self,
        room_id: str,
        records: list[TrackRecord],
        ids: list[str],
        terminals: list[str | None],
        tracks: Tracks,
        rows: np.ndarray,
    ) -> dict[str, TrackRecord]:
        """The records of the tracks at ``rows`` (a mask) as they are now."""
        now = self._clock.now()
        mean, covariance = estimates(tracks.bank)
        radii = confidence_radii(covariance[:, :2, :2])
        out = {}
        for row in np.nonzero(rows)[0]:
            previous = records[row] if row < len(records) else None
            out[ids[row]] = TrackRecord(
                id=ids[row],
                room_id=room_id,
                terminal_id=terminals[row],
                status=STATUS_NAMES[int(tracks.status[row])],
                filter=filter_json(tracks.bank, int(row)) | rival_json(tracks, int(row), ids),
                x=float(mean[row, 0]),
                y=float(mean[row, 1]),
                vx=float(mean[row, 2]),
                vy=float(mean[row, 3]),
                covariance=covariance[row, :2, :2].tolist(),
                accuracy_m=float(radii[row]),
                state_time=to_time(float(tracks.bank.times_s[row])),
                created_at=now if previous is None else previous.created_at,
                updated_at=now,
                updates=int(tracks.updates[row]),
                misses=int(tracks.misses[row]),
                last_raw=None if previous is None else previous.last_raw,
            )
        return out

    def _changes(
        self,
        room_id: str,
        records: list[TrackRecord],
        ids: list[str],
        written: dict[str, TrackRecord],
        removed: np.ndarray,
        fixes: _Fixes,
        fix_rows: IntArray,
        when: datetime,
        settings: TrackerSettings,
    ) -> TrackChanges:
        """Rows, history points and events of one update."""
        known = {r.id: r for r in records} | written
        points = []
        for k, row in enumerate(fix_rows):
            state = known[ids[row]]
            raw = _raw(fixes, k)
            points.append(
                TrackPointRecord(
                    track_id=state.id,
                    time=when,
                    x=state.x,
                    y=state.y,
                    accuracy_m=state.accuracy_m,
                    raw_x=raw["x"],
                    raw_y=raw["y"],
                    raw_accuracy_m=raw["accuracy_m"],
                )
            )
        ended = [ids[row] for row in np.nonzero(removed)[0] if row < len(records)]
        events = [
            ("track", r.id, track_public(r).model_dump(mode="json")) for r in written.values()
        ]
        events += [("removed", track_id, {"id": track_id}) for track_id in ended]
        history = timedelta(seconds=settings.history_s)
        now = self._clock.now()
        prune = self._prune_due(room_id, now, history)
        return TrackChanges(
            upserts=tuple(written.values()),
            removed=tuple(ended),
            points=tuple(points),
            events=tuple(events),
            points_before=when - history if prune else None,
            events_before=now - history if prune else None,
        )

    def _prune_due(self, room_id: str, now: datetime, history: timedelta) -> bool:
        """Whether this update deletes the room's old history (:data:`PRUNES_PER_HISTORY`);
        if so it is noted as done."""
        last = self._pruned.get(room_id)
        if last is not None and timedelta(0) <= now - last < history / PRUNES_PER_HISTORY:
            return False
        self._pruned[room_id] = now
        return True

    def _announce(self, room_id: str, sequence: int) -> None:
        if self._on_event is not None:
            self._on_event(room_id, sequence)

    # -- time passing ---------------------------------------------------------------------
    def sweep(self) -> int:
        """Mark tracks lost and end them as the clock says; how many events that made.

        A room is locked only when a read shows that something is due."""
        now = self._clock.now()
        events = 0
        for room_id in self._registry.tracks.rooms_with_tracks():
            records = self._registry.tracks.all_tracks(room_id=room_id)
            stored = self._registry.tracks.get_settings(room_id=room_id)
            if _due(records, tracker_settings(stored), now):
                events += self._sweep_room(room_id, now)
        return events

    def _sweep_room(self, room_id: str, now: datetime) -> int:
        def apply(current: list[TrackRecord], stored: dict[str, Any] | None) -> TrackChanges:
            return self._aged(room_id, current, tracker_settings(stored), now)

        try:
            changes, sequence = self._registry.tracks.update_room(
                room_id=room_id, now=now, apply=apply
            )
        except RecordNotFound:
            return 0  # the room was deleted meanwhile
        self._announce(room_id, sequence)
        return len(changes.events)

    def _aged(
        self, room_id: str, records: list[TrackRecord], settings: TrackerSettings, now: datetime
    ) -> TrackChanges:
        tracks = tracks_of(records)
        status, removed = age_tracks(tracks, seconds(now), settings)
        changed = np.array(
            [STATUS_NAMES[status[i]] != r.status for i, r in enumerate(records)], dtype=bool
        )
        tracks = dataclasses.replace(tracks, status=status)
        ids = [r.id for r in records]
        terminals = [r.terminal_id for r in records]
        written = self._records(room_id, records, ids, terminals, tracks, changed & ~removed)
        ended = [ids[row] for row in np.nonzero(removed)[0]]
        events = [
            ("track", r.id, track_public(r).model_dump(mode="json")) for r in written.values()
        ]
        events += [("removed", track_id, {"id": track_id}) for track_id in ended]
        return TrackChanges(
            upserts=tuple(written.values()), removed=tuple(ended), events=tuple(events)
        )

    # -- resources ------------------------------------------------------------------------
    def delete(self, *, room_id: str, track_id: str) -> None:
        """End a track now (its ``removed`` event goes out). TrackNotFound, RoomNotFound."""
        self._registry.tracks.get_track(room_id=room_id, track_id=track_id)

        def apply(current: list[TrackRecord], stored: dict[str, Any] | None) -> TrackChanges:
            del stored
            if not any(r.id == track_id for r in current):
                return TrackChanges()
            return TrackChanges(
                removed=(track_id,), events=(("removed", track_id, {"id": track_id}),)
            )

        changes, sequence = self._registry.tracks.update_room(
            room_id=room_id, now=self._clock.now(), apply=apply
        )
        if not changes.removed:
            raise TrackNotFound(f"room {room_id} has no track {track_id!r}", field="track_id")
        self._announce(room_id, sequence)


def _due(records: list[TrackRecord], settings: TrackerSettings, now: datetime) -> bool:
    """Whether ageing would change any of the tracks at ``now``."""
    for record in records:
        idle = (now - record.state_time).total_seconds()
        if idle > settings.drop_after_s or (
            idle > settings.lost_after_s and record.status != "lost"
        ):
            return True
    return False


def _take(tracks: Tracks, rows: IntArray) -> Tracks:
    return tracks.take(rows)


def _merge(tracks: Tracks, rows: IntArray, part: Tracks) -> Tracks:
    """``tracks`` with its ``rows`` replaced by ``part``'s first rows and ``part``'s other
    rows appended."""
    head = part.take(np.arange(rows.size, dtype=np.intp))
    tail = part.take(np.arange(rows.size, part.size, dtype=np.intp))
    return joined(tracks.put(rows, head), tail)


def _raw(fixes: _Fixes, k: int) -> dict[str, float]:
    return {
        "x": float(fixes.positions[k, 0]),
        "y": float(fixes.positions[k, 1]),
        "accuracy_m": float(fixes.radii[k]),
    }


def _with_raw(record: TrackRecord, fixes: _Fixes, k: int) -> TrackRecord:
    return dataclasses.replace(record, last_raw=_raw(fixes, k))
