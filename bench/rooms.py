"""Rooms the accuracy benchmark runs in: the paper's room and a harder one of our own.

The harder room (``"hall"``) changes everything the paper keeps regular: it is larger and
not square (8 x 6 x 3.5 m), the grid is coarser (0.25 m, N = 768), the 20 LEDs are an
irregular pattern (a 7 x 3 array with each LED moved by up to 0.3 m and one LED missing),
their half-power angles mix 45, 60 and 70 degrees, and the receivers' FOV is 65 degrees.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.presets import paper_layout

__all__ = ["ROOMS", "hall_layout", "make_room"]

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


ROOMS: dict[str, Callable[[], Layout]] = {"paper": paper_layout, "hall": hall_layout}


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
