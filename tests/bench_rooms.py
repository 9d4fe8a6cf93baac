"""A small room for the benchmarks' smoke runs (tests/bench), and its fixture (a plugin of
tests/conftest.py: tests/bench is no package, and a conftest.py there would clash with
tests/conftest.py by module name)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from bench import rooms

SMALL_ROOM = "small"
# The small room's size (m): a smoke run's errors are checked against a fraction of it.
SMALL_ROOM_SIDE_M = 2.4


def small_room_layout() -> Layout:
    """A 2.4 x 2.4 x 3 m room with 4 LEDs (2 x 2, 1.2 m apart), the paper room's beams,
    receiver and 0.2 m grid (N = 144).

    A smoke run in it does what it does in the benchmarks' rooms (surveys, calibrations,
    reflection tables, solves) at a fraction of the cost: a reflection table's build, most of
    a run with reflectance in the layout, grows with the room's floor and its LED count."""
    step = SMALL_ROOM_SIDE_M / 2
    leds = tuple(
        Led(
            x=step * (i + 0.5),
            y=step * (j + 0.5),
            z=3.0,
            half_power_angle_deg=60.0,
            pilot_amplitude=1.0,
        )
        for i in range(2)
        for j in range(2)
    )
    return Layout(
        room=Room(length=SMALL_ROOM_SIDE_M, width=SMALL_ROOM_SIDE_M, height=3.0),
        grid=Grid(step=0.2, receiver_height=0.85),
        leds=leds,
        receiver=Receiver(area=1e-4, fov_deg=70.0, filter_gain=1.0, refractive_index=1.5),
        name="Small room (2.4 x 2.4 m, 4 LEDs)",
    )


@pytest.fixture
def small_room() -> Iterator[str]:
    """:func:`small_room_layout` registered among the benchmarks' rooms for one test: its
    name, for a benchmark's ``--rooms``."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(rooms.ROOMS, SMALL_ROOM, small_room_layout)
        yield SMALL_ROOM
