"""The example rooms of the kernel table (:mod:`._kernel_examples`): the paper room, one LED
above a small room, tilted LEDs, batwing beams, each with no reflection table or a
synthetic one (random node values: the interpolation does not care what they mean) on the
receivers' plane or around it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from .._reflection_table import ReflectionTable
from ..layout import Beam, Grid, Layout, Led, Receiver, Room
from ..presets import paper_layout
from .gridless.channel import ChannelKernel

__all__ = [
    "LAYOUTS",
    "TABLES",
    "beamed_layout",
    "make_kernel",
    "one_led_layout",
    "synthetic_table",
    "tilted_layout",
]


def one_led_layout() -> Layout:
    """M = 1: one LED above a small room, off the grid's symmetries. With one LED a cell's
    score depends on its distance alone; an LED as far from the cells' centres in x as in y
    puts pairs of cells at exactly one distance, and the compiled and the Python growth
    steps then pick either by round-off."""
    return Layout(
        room=Room(length=3.0, width=2.0, height=2.8),
        grid=Grid(step=0.25, receiver_height=0.8),
        leds=(Led(x=1.4, y=0.95, z=2.8, half_power_angle_deg=50.0, pilot_amplitude=1.3),),
        receiver=Receiver(area=1e-4, fov_deg=75.0, filter_gain=1.0, refractive_index=1.5),
    )


def tilted_layout() -> Layout:
    """The paper room with every other LED tilted (10 to 20 degrees, various azimuths)."""
    base = paper_layout()
    leds = []
    for i, led in enumerate(base.leds):
        if i % 2:
            tilt, azimuth = math.radians(10.0 + 2.5 * (i % 5)), 0.9 * i
            normal = (
                math.sin(tilt) * math.cos(azimuth),
                math.sin(tilt) * math.sin(azimuth),
                -math.cos(tilt),
            )
            led = dataclasses.replace(led, normal=normal)
        leds.append(led)
    return dataclasses.replace(base, leds=tuple(leds))


def beamed_layout() -> Layout:
    """The tilted room with batwing beams (photometric tables) on all but one LED."""
    base = tilted_layout()
    batwing = Beam(
        (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0), (1.0, 1.05, 1.12, 1.1, 0.7, 0.3, 0.05)
    )
    leds = tuple(
        dataclasses.replace(led, beam=batwing if i else None) for i, led in enumerate(base.leds)
    )
    return dataclasses.replace(base, leds=leds)


LAYOUTS: dict[str, Callable[[], Layout]] = {
    "paper": paper_layout,
    "one_led": one_led_layout,
    "tilted": tilted_layout,
    "beamed": beamed_layout,
}
TABLES = ("none", "flat", "heights")


def synthetic_table(
    layout: Layout, heights: bool, seed: int, magnitude: float = 1.0
) -> ReflectionTable:
    """A reflection table with random node values (the interpolation does not care what
    they mean) up to ``magnitude``, on 2 or 3 axes."""
    rng = np.random.default_rng(seed)
    x_nodes = np.unique(np.r_[np.linspace(0.0, layout.room.length, 7), 0.05])
    y_nodes = np.linspace(0.0, layout.room.width, 5)
    z = layout.grid.receiver_height
    z_nodes = np.linspace(z - 0.3, z + 0.3, 4) if heights else np.array([z])
    terms = 8 if heights else 4
    coefficients = rng.uniform(-1.0, 1.0, (x_nodes.size * y_nodes.size * z_nodes.size, terms, 1))
    coefficients = coefficients * rng.uniform(0.5, 2.0, (1, 1, layout.n_leds)) * magnitude
    return ReflectionTable(x_nodes, y_nodes, z_nodes, coefficients, z)


def make_kernel(layout_name: str, table: str, seed: int = 0) -> ChannelKernel:
    """The channel of a layout of :data:`LAYOUTS`, without a reflection table (``"none"``)
    or with a synthetic one on the receivers' plane (``"flat"``) or around it
    (``"heights"``)."""
    layout = LAYOUTS[layout_name]()
    diffuse = None if table == "none" else synthetic_table(layout, table == "heights", seed)
    return ChannelKernel(layout, 0.7, diffuse)
