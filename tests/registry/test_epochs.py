"""Epochs in the registry: pinning, posts and replacement, exactly-once claims, leases, purge.

The registry runs on a :class:`FakeClock` that no test advances: windows and claims end at the
times the tests name (``seconds_later``), not when the machine gets there.
"""

from __future__ import annotations

import threading
from datetime import timedelta
from functools import partial
from typing import Any

import pytest

from app.clock import FakeClock
from app.errors import InvalidFields
from app.registry import Registry
from app.registry.errors import (
    EpochClosed,
    EpochFull,
    EpochNotFound,
    FingerprintNotFound,
    FingerprintNotReady,
    RoomNotFound,
)
from app.registry.records import ClaimedEpoch, EpochRecord, EpochSettings
from app.services.epochs import open_epoch, post_to_epoch
from app.vlp.errors import MeasurementError
from tests.db_fixtures import build_now, small_layout

N_LEDS = 3


def wanted(**changes: object) -> EpochSettings:
    values: dict[str, object] = {
        "model": "correlation",
        "solver": "gridless",
        "targets": None,
        "min_terminals": 2,
        "max_terminals": 4,
        "window_s": 60.0,
        "fingerprint_version": 0,
        "leds": 0,
    }
    values.update(changes)
    return EpochSettings(**values)  # type: ignore[arg-type]


@pytest.fixture
def clock() -> FakeClock:
    """The registry's clock (overrides the real one of ``tests/db_fixtures.py``)."""
    return FakeClock()


@pytest.fixture
def room_id(registry: Registry) -> str:
    room = registry.create_room(name="Small", layout=small_layout(N_LEDS))
    build_now(registry, room_id=room.id)
    return room.id


@pytest.fixture
def epoch(registry: Registry, room_id: str) -> EpochRecord:
    return open_epoch(registry, room_id=room_id, settings=wanted())


def claim(
    registry: Registry, epoch: EpochRecord, owner: str, *, seconds_later: float = 0.0, **kw: object
) -> ClaimedEpoch | None:
    options: dict[str, object] = {"lease_s": 30.0, "max_attempts": 3, "force": True}
    options.update(kw)
    return registry.epochs.claim(
        room_id=epoch.room_id,
        epoch_id=epoch.id,
        owner=owner,
        now=registry.clock.now() + timedelta(seconds=seconds_later),
        **options,  # type: ignore[arg-type]
    )


def test_create_pins_the_current_fingerprint_and_its_led_count(
    registry: Registry, epoch: EpochRecord
) -> None:
    assert epoch.status == "open" and epoch.terminals == 0 and epoch.attempts == 0
    assert epoch.settings.fingerprint_version == 1 and epoch.settings.leds == N_LEDS
    assert epoch.settings.min_terminals == 2 and epoch.settings.window_s == 60.0
    assert epoch.expires_at - epoch.created_at == timedelta(seconds=60)
    assert registry.epochs.get(room_id=epoch.room_id, epoch_id=epoch.id) == epoch


def test_create_needs_a_known_room_and_a_ready_fingerprint(registry: Registry) -> None:
    with pytest.raises(RoomNotFound):
        open_epoch(registry, room_id="nope", settings=wanted())
    room = registry.create_room(name="Unbuilt", layout=small_layout())
    with pytest.raises(FingerprintNotReady):
        open_epoch(registry, room_id=room.id, settings=wanted())
    build_now(registry, room_id=room.id)
    with pytest.raises(FingerprintNotFound):
        open_epoch(registry, room_id=room.id, settings=wanted(), fingerprint_version=7)


def test_a_terminal_posting_again_replaces_its_amplitudes(
    registry: Registry, epoch: EpochRecord
) -> None:
    post = partial(post_to_epoch, registry)
    post(room_id=epoch.room_id, epoch_id=epoch.id, terminal_id="t1", amplitudes=[1.0, 2.0, 3.0])
    post(room_id=epoch.room_id, epoch_id=epoch.id, terminal_id="t2", amplitudes=[4.0, 5.0, 6.0])
    again = post(
        room_id=epoch.room_id, epoch_id=epoch.id, terminal_id="t1", amplitudes=[7.0, 8.0, 9.5]
    )
    assert again.terminals == 2
    claimed = claim(registry, epoch, "solver-a")
    assert claimed is not None
    assert dict(zip(claimed.terminal_ids, claimed.amplitudes, strict=True)) == {
        "t1": (7.0, 8.0, 9.5),
        "t2": (4.0, 5.0, 6.0),
    }


def test_undetected_leds_and_floors_are_stored_as_sent(
    registry: Registry, epoch: EpochRecord
) -> None:
    post = partial(post_to_epoch, registry, room_id=epoch.room_id, epoch_id=epoch.id)
    post(terminal_id="t1", amplitudes=[None, 2.0, None], detection_floor=0.5)
    post(terminal_id="t2", amplitudes=[4.0, None, 6.0])
    post(terminal_id="t3", amplitudes=[1.0, 1.0, 1.0], detection_floor=0.25)
    post(terminal_id="t3", amplitudes=[None, 3.0, 3.0])  # a repost without a floor drops it
    claimed = claim(registry, epoch, "solver-a")
    assert claimed is not None
    stored = zip(claimed.terminal_ids, claimed.amplitudes, claimed.detection_floors, strict=True)
    assert {tid: (amplitudes, floor) for tid, amplitudes, floor in stored} == {
        "t1": ((None, 2.0, None), 0.5),
        "t2": ((4.0, None, 6.0), None),
        "t3": ((None, 3.0, 3.0), None),
    }


def test_a_post_that_detected_no_led_is_refused_naming_its_amplitudes(
    registry: Registry, epoch: EpochRecord
) -> None:
    with pytest.raises(InvalidFields) as info:
        post_to_epoch(
            registry,
            room_id=epoch.room_id,
            epoch_id=epoch.id,
            terminal_id="t1",
            amplitudes=[None, None, None],
        )
    assert [field for field, _ in info.value.errors] == ["amplitudes"]
    assert registry.epochs.get(room_id=epoch.room_id, epoch_id=epoch.id).terminals == 0


def test_posts_are_refused_when_wrong_closed_full_or_unknown(
    registry: Registry, room_id: str
) -> None:
    epoch = open_epoch(registry, room_id=room_id, settings=wanted(max_terminals=2))
    ids: dict[str, Any] = {"room_id": room_id, "epoch_id": epoch.id}
    with pytest.raises(MeasurementError, match="expected 3 amplitudes") as info:
        post_to_epoch(registry, **ids, terminal_id="t1", amplitudes=[1.0, 2.0])
    assert info.value.field == "amplitudes"
    for terminal in ("t1", "t2", "t2"):
        post_to_epoch(registry, **ids, terminal_id=terminal, amplitudes=[1.0, 1.0, 1.0])
    with pytest.raises(EpochFull):
        post_to_epoch(registry, **ids, terminal_id="t3", amplitudes=[1.0, 1.0, 1.0])
    with pytest.raises(EpochClosed, match="window"):
        registry.epochs.post_measurement(
            **ids,
            terminal_id="t1",
            amplitudes=[1.0, 1.0, 1.0],
            now=epoch.expires_at,
        )
    with pytest.raises(EpochNotFound):
        post_to_epoch(
            registry, room_id=room_id, epoch_id="nope", terminal_id="t1", amplitudes=[1.0, 1.0, 1.0]
        )
    other = registry.create_room(name="Other", layout=small_layout())
    with pytest.raises(EpochNotFound):
        registry.epochs.get(room_id=other.id, epoch_id=epoch.id)
    assert claim(registry, epoch, "solver-a") is not None
    with pytest.raises(EpochClosed, match="solving"):
        post_to_epoch(registry, **ids, terminal_id="t1", amplitudes=[1.0, 1.0, 1.0])
    assert registry.epochs.get(**ids).terminals == 2


def test_only_one_of_many_concurrent_claims_wins(registry: Registry, epoch: EpochRecord) -> None:
    barrier = threading.Barrier(6)
    results: list[ClaimedEpoch | None] = []
    lock = threading.Lock()

    def contend(owner: str) -> None:
        barrier.wait()
        outcome = claim(registry, epoch, owner)
        with lock:
            results.append(outcome)

    threads = [threading.Thread(target=contend, args=(f"p{i}",)) for i in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    winners = [result for result in results if result is not None]
    assert len(results) == 6 and len(winners) == 1
    state = registry.epochs.get(room_id=epoch.room_id, epoch_id=epoch.id)
    assert state.status == "solving" and state.attempts == 1


def test_an_open_window_is_claimed_only_when_due_or_forced(
    registry: Registry, epoch: EpochRecord
) -> None:
    assert claim(registry, epoch, "sweeper", force=False) is None
    assert registry.epochs.due(now=registry.clock.now(), limit=10) == []
    later = epoch.expires_at + timedelta(seconds=1)
    assert registry.epochs.due(now=later, limit=10) == [(epoch.room_id, epoch.id)]
    assert claim(registry, epoch, "sweeper", force=False, seconds_later=61) is not None


def test_a_lost_solver_is_taken_over_and_cannot_overwrite(
    registry: Registry, epoch: EpochRecord
) -> None:
    first = claim(registry, epoch, "crashed")
    assert first is not None
    assert claim(registry, epoch, "impatient") is None  # the lease still runs
    second = claim(registry, epoch, "heir", seconds_later=31)
    assert second is not None and second.record.attempts == 2
    assert not registry.epochs.finish(claimed=first, status="solved", now=registry.clock.now())
    assert registry.epochs.finish(
        claimed=second,
        status="solved",
        now=registry.clock.now(),
        localization={"k": 1},
    )
    done = registry.epochs.get(room_id=epoch.room_id, epoch_id=epoch.id)
    assert done.status == "solved" and done.localization == {"k": 1}
    assert claim(registry, epoch, "late", seconds_later=3600) is None


def test_an_epoch_whose_solver_is_lost_too_often_fails(
    registry: Registry, epoch: EpochRecord
) -> None:
    for attempt in range(3):
        assert claim(registry, epoch, f"p{attempt}", seconds_later=31 * attempt) is not None
    assert claim(registry, epoch, "p3", seconds_later=31 * 3) is None
    failed = registry.epochs.get(room_id=epoch.room_id, epoch_id=epoch.id)
    assert failed.status == "failed" and failed.error is not None and "3 times" in failed.error


def test_purge_drops_old_finished_epochs_with_their_posts(
    registry: Registry, room_id: str, epoch: EpochRecord
) -> None:
    post_to_epoch(
        registry, room_id=room_id, epoch_id=epoch.id, terminal_id="t1", amplitudes=[1.0, 1.0, 1.0]
    )
    still_open = open_epoch(registry, room_id=room_id, settings=wanted())
    claimed = claim(registry, epoch, "p")
    assert claimed is not None
    assert registry.epochs.finish(claimed=claimed, status="expired", now=registry.clock.now())
    assert registry.epochs.purge(finished_before=registry.clock.now() - timedelta(hours=1)) == 0
    assert registry.epochs.purge(finished_before=registry.clock.now() + timedelta(seconds=1)) == 1
    with pytest.raises(EpochNotFound):
        registry.epochs.get(room_id=room_id, epoch_id=epoch.id)
    assert registry.epochs.get(room_id=room_id, epoch_id=still_open.id).status == "open"


def test_deleting_the_room_deletes_its_epochs(
    registry: Registry, room_id: str, epoch: EpochRecord
) -> None:
    post_to_epoch(
        registry, room_id=room_id, epoch_id=epoch.id, terminal_id="t1", amplitudes=[1.0, 1.0, 1.0]
    )
    registry.delete_room(room_id=room_id)
    with pytest.raises(EpochNotFound):
        registry.epochs.get(room_id=room_id, epoch_id=epoch.id)


def test_finish_takes_only_final_statuses(registry: Registry, epoch: EpochRecord) -> None:
    claimed = claim(registry, epoch, "p")
    assert claimed is not None
    with pytest.raises(ValueError, match="finishes as one of"):
        registry.epochs.finish(claimed=claimed, status="open", now=registry.clock.now())
