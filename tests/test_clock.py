"""The clocks of app/clock.py: the system clock is aware UTC, the fake one moves when told."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest

from app.clock import Clock, FakeClock, SystemClock


def test_fake_clock_stands_still_until_advanced_and_moves_both_readings() -> None:
    start = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    clock = FakeClock(start)
    assert (clock.now(), clock.monotonic()) == (start, 0.0)
    assert (clock.now(), clock.monotonic()) == (start, 0.0)
    clock.advance(1.5)
    clock.advance(0.0)
    assert clock.now() == start + timedelta(seconds=1.5)
    assert clock.monotonic() == 1.5


def test_fake_clock_refuses_to_go_back_or_to_start_naive() -> None:
    clock = FakeClock()
    with pytest.raises(ValueError, match="forward"):
        clock.advance(-0.001)
    with pytest.raises(ValueError, match="forward"):
        clock.advance(float("nan"))
    with pytest.raises(ValueError, match="timezone-aware"):
        FakeClock(datetime(2026, 1, 1))


def test_fake_clock_reports_utc_whatever_zone_it_started_in() -> None:
    plus_two = timezone(timedelta(hours=2))
    clock = FakeClock(datetime(2026, 1, 1, 12, 0, tzinfo=plus_two))
    assert clock.now() == datetime(2026, 1, 1, 10, 0, tzinfo=UTC)
    assert clock.now().utcoffset() == timedelta(0)


def test_system_clock_is_aware_utc_and_monotonic_never_goes_back() -> None:
    clock: Clock = SystemClock()
    now = clock.now()
    assert now.utcoffset() == timedelta(0)
    assert abs(now - datetime.now(UTC)) < timedelta(hours=1)  # the real date, not an epoch
    first = clock.monotonic()
    assert clock.monotonic() >= first
