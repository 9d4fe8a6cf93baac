"""Rooms the accuracy benchmark runs in: the paper's room and a harder one of our own.

The harder room (``"hall"``) changes everything the paper keeps regular: it is larger and
not square (8 x 6 x 3.5 m), the grid is coarser (0.25 m, N = 768), the 20 LEDs are an
irregular pattern (a 7 x 3 array with each LED moved by up to 0.3 m and one LED missing),
their half-power angles mix 45, 60 and 70 degrees, and the receivers' FOV is 65 degrees.

Two more rooms check solver changes on rooms they were not developed on (``"office"``, a low
ceiling with 12 LEDs; ``"corridor"``, long and narrow with two rows of mixed beams); the
published tables stay on the first two.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.presets import paper_layout

__all__ = ["ROOMS", "corridor_layout", "hall_layout", "make_room", "office_layout"]

# Fixed seed of the hall's LED jitter and beam widths (the layout never changes).
_HALL_SEED = 20261122
_HALL_COLUMNS = 7
_HALL_ROWS = 3
_HALL_JITTER_M = 0.3
_HALL_MISSING = 9  # index (column-major) of the nominal LED left out: column 3, row 0
_HALL_HALF_POWER_ANGLES_DEG = (45.0, 60.0, 70.0)


def hall_layout() -> Layout:
    """The harder room: 8 x 6 x 3.5 m, 0.25 m grid at 0.85 m, 20 irregular mixed-beam LEDs.

    Returns
    -------
    Layout
        M = 20 LEDs at z = 3.5 m, N = 32 x 24 = 768 grid points, FOV 65 degrees, 1 cm^2
        detector.
    """
    length, width, height = 8.0, 6.0, 3.5
    gen = np.random.default_rng(_HALL_SEED)
    leds = []
    for column in range(_HALL_COLUMNS):
        for row in range(_HALL_ROWS):
            index = column * _HALL_ROWS + row
            jitter = gen.uniform(-_HALL_JITTER_M, _HALL_JITTER_M, size=2)
            angle = float(gen.choice(_HALL_HALF_POWER_ANGLES_DEG))
            if index == _HALL_MISSING:
                continue
            x = (column + 0.5) * length / _HALL_COLUMNS + jitter[0]
            y = (row + 0.5) * width / _HALL_ROWS + jitter[1]
            leds.append(
                Led(
                    x=round(float(x), 2),
                    y=round(float(y), 2),
                    z=height,
                    half_power_angle_deg=angle,
                    pilot_amplitude=1.0,
                )
            )
    return Layout(
        room=Room(length=length, width=width, height=height),
        grid=Grid(step=0.25, receiver_height=0.85),
        leds=tuple(leds),
        receiver=Receiver(area=1e-4, fov_deg=65.0, filter_gain=1.0, refractive_index=1.5),
        name="Hall (8 x 6 m, irregular mixed-beam LEDs)",
    )


def office_layout() -> Layout:
    """A low office: 6 x 4.2 x 2.8 m, 0.2 m grid at 0.8 m, a 4 x 3 array of 50-degree LEDs.

    Returns
    -------
    Layout
        M = 12 LEDs at z = 2.8 m, N = 30 x 21 = 630 grid points, FOV 70 degrees.
    """
    leds = tuple(
        Led(x=0.75 + 1.5 * column, y=0.7 + 1.4 * row, z=2.8, half_power_angle_deg=50.0)
        for column in range(4)
        for row in range(3)
    )
    return Layout(
        room=Room(length=6.0, width=4.2, height=2.8),
        grid=Grid(step=0.2, receiver_height=0.8),
        leds=leds,
        receiver=Receiver(area=1e-4, fov_deg=70.0, filter_gain=1.0, refractive_index=1.5),
        name="Office (6 x 4.2 m, 12 LEDs)",
    )


def corridor_layout() -> Layout:
    """A corridor: 9.6 x 2 x 3 m, 0.2 m grid at 0.9 m, two rows of 8 LEDs, 45 and 60 degrees
    alternating along it.

    Returns
    -------
    Layout
        M = 16 LEDs at z = 3 m, N = 48 x 10 = 480 grid points, FOV 75 degrees.
    """
    leds = tuple(
        Led(
            x=0.6 + 1.2 * column,
            y=0.5 + 1.0 * row,
            z=3.0,
            half_power_angle_deg=60.0 if column % 2 else 45.0,
        )
        for column in range(8)
        for row in range(2)
    )
    return Layout(
        room=Room(length=9.6, width=2.0, height=3.0),
        grid=Grid(step=0.2, receiver_height=0.9),
        leds=leds,
        receiver=Receiver(area=1e-4, fov_deg=75.0, filter_gain=1.0, refractive_index=1.5),
        name="Corridor (9.6 x 2 m, 16 LEDs)",
    )


ROOMS: dict[str, Callable[[], Layout]] = {
    "paper": paper_layout,
    "hall": hall_layout,
    "office": office_layout,
    "corridor": corridor_layout,
}


def make_room(name: str) -> Layout:
    """The layout registered under ``name`` in :data:`ROOMS`.

    Raises
    ------
    KeyError
        When no room has that name.
    """
    try:
        return ROOMS[name]()
    except KeyError:
        raise KeyError(f"unknown room {name!r}; choose one of {sorted(ROOMS)}") from None
