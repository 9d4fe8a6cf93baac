"""Fixtures of the benchmarks' smoke runs."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from bench import rooms
from tests.bench_rooms import SMALL_ROOM, small_room_layout


@pytest.fixture
def small_room() -> Iterator[str]:
    """:func:`small_room_layout` registered among the benchmarks' rooms for one test: its
    name, for a benchmark's ``--rooms``."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(rooms.ROOMS, SMALL_ROOM, small_room_layout)
        yield SMALL_ROOM
