"""Tracks as stored and back: the pairs followed both ways after an ambiguous solve."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
from numpy.testing import assert_allclose

from app.registry.records import TrackRecord
from app.services._track_state import filter_json, rival_json, to_time, tracks_of
from app.vlp.tracking import STATUS_NAMES, TrackerSettings, Tracks, step_anonymous


def _records(tracks: Tracks, ids: list[str]) -> list[TrackRecord]:
    now = datetime(2026, 1, 1, tzinfo=UTC)
    return [
        TrackRecord(
            id=ids[row],
            room_id="room",
            terminal_id=None,
            status=STATUS_NAMES[int(tracks.status[row])],
            filter=filter_json(tracks.bank, row) | rival_json(tracks, row, ids),
            x=0.0,
            y=0.0,
            vx=0.0,
            vy=0.0,
            covariance=[[1.0, 0.0], [0.0, 1.0]],
            accuracy_m=1.0,
            state_time=to_time(float(tracks.bank.times_s[row])),
            created_at=now,
            updated_at=now,
            updates=int(tracks.updates[row]),
            misses=int(tracks.misses[row]),
            last_raw=None,
        )
        for row in range(tracks.size)
    ]


def test_a_pair_followed_both_ways_is_stored_and_read_back() -> None:
    # Two walkers meeting head-on, a third standing apart: the first two are paired where
    # they meet.
    settings = TrackerSettings()
    noise = np.tile(0.03**2 * np.eye(2), (3, 1, 1))
    tracks, time_s = Tracks.empty(), 1.8e9
    for k in range(10):  # they meet between solves 9 and 10
        time_s += 0.2
        fixes = np.array([[0.5 + 0.28 * k, 2.0], [5.82 - 0.28 * k, 2.0], [1.0, 6.0]])
        tracks = step_anonymous(tracks, fixes, noise, time_s, settings).tracks
    assert tracks.rivals is not None
    assert tracks.rivals.pair.tolist() == [1, 1, 0]
    ids = ["a", "b", "c"]
    records = _records(tracks, ids)
    assert records[0].filter["rival"]["with"] == "b"
    assert "rival" not in records[2].filter
    back = tracks_of(records)
    assert back.rivals is not None
    assert back.rivals.pair.tolist() == [1, 1, 0]
    assert_allclose(back.rivals.score[:2], tracks.rivals.score[:2])
    assert back.rivals.solves[:2].tolist() == tracks.rivals.solves[:2].tolist()
    for name in ("means", "covariances", "model_probabilities", "times_s", "noise_var"):
        assert_allclose(getattr(back.rivals.bank, name)[:2], getattr(tracks.rivals.bank, name)[:2])
    # A pair whose other track has gone ends.
    alone = tracks_of(records[:1] + records[2:])
    assert alone.rivals is None
