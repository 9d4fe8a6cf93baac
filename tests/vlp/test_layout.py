"""Layouts: validation names the bad field; grid order; mapping round trip."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.errors import GeometryError
from app.vlp.layout import (
    Grid,
    Layout,
    Led,
    Receiver,
    Reflectance,
    Room,
)
from app.vlp.layout_mapping import layout_from_mapping


def _mapping() -> dict[str, Any]:
    return {
        "name": "test",
        "room": {"length": 3.0, "width": 2.0, "height": 3.0},
        "grid": {"step": 0.5, "receiver_height": 0.85},
        "leds": [
            {"x": 1.0, "y": 1.0},
            {"x": 2.0, "y": 0.5, "z": 2.5, "half_power_angle_deg": 45.0, "pilot_amplitude": 2.0},
        ],
    }


def test_mapping_defaults_and_round_trip() -> None:
    layout = layout_from_mapping(_mapping())
    assert layout.leds[0] == Led(1.0, 1.0, 3.0, 60.0, 1.0)  # z = room height, defaults
    assert layout.receiver == Receiver(1e-4, 70.0, 1.0, 1.5)
    assert layout.n_x == 6 and layout.n_y == 4 and layout.n_cells == 24
    assert layout_from_mapping(layout.to_mapping()) == layout


def test_grid_order_and_nearest_cell() -> None:
    layout = layout_from_mapping(_mapping())
    centres = layout.cell_centres()
    expected = np.array(
        [[(ix + 0.5) * 0.5, (iy + 0.5) * 0.5] for ix in range(6) for iy in range(4)]
    )  # j = ix * n_y + iy
    assert_allclose(centres, expected)
    assert_array_equal(layout.nearest_cell(centres), np.arange(24))
    assert_array_equal(layout.nearest_cell(np.array([[-1.0, 9.0]])), [3])  # clipped


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda m: m["grid"].update(step=0.7), "grid.step"),
        (lambda m: m["room"].update(length=-1.0), "room.length"),
        (lambda m: m["grid"].update(receiver_height=3.5), "grid.receiver_height"),
        (lambda m: m["grid"].update(receiver_height=-0.1), "grid.receiver_height"),
        (lambda m: m["leds"][1].update(x=3.5), "leds[1].x"),
        (lambda m: m["leds"][0].update(y=-0.1), "leds[0].y"),
        (lambda m: m["leds"][1].update(z=0.5), "leds[1].z"),
        (lambda m: m["leds"][0].update(half_power_angle_deg=90.0), "leds[0].half_power_angle_deg"),
        (lambda m: m["leds"][0].update(pilot_amplitude=0.0), "leds[0].pilot_amplitude"),
        (lambda m: m.update(receiver={"fov_deg": 95.0}), "receiver.fov_deg"),
        (lambda m: m.update(receiver={"area": 0.0}), "receiver.area"),
        (lambda m: m.update(receiver={"refractive_index": 0.5}), "receiver.refractive_index"),
        (lambda m: m.update(leds=[]), "leds"),
    ],
    ids=[
        "step",
        "length",
        "rx-height",
        "rx-height-negative",
        "led-x",
        "led-y",
        "led-z",
        "half-power",
        "pilot",
        "fov",
        "area",
        "index",
        "no-leds",
    ],
)
def test_validation_names_the_field(change: Any, field: str) -> None:
    mapping = _mapping()
    change(mapping)
    with pytest.raises(GeometryError) as info:
        layout_from_mapping(mapping)
    assert info.value.field == field
    assert field.split(".")[-1].split("[")[0].rstrip("s") in str(info.value).lower()


def test_incomplete_mapping() -> None:
    mapping = _mapping()
    del mapping["grid"]
    with pytest.raises(GeometryError, match="incomplete"):
        layout_from_mapping(mapping)


def test_led_arrays() -> None:
    layout = Layout(
        Room(2, 2, 3), Grid(1.0, 0.5), (Led(0.5, 0.5, 3.0, 30.0, 2.0), Led(1.5, 1.0, 2.0))
    )
    assert_allclose(layout.led_positions, [[0.5, 0.5, 3.0], [1.5, 1.0, 2.0]])
    assert_allclose(layout.half_power_angles_deg, [30.0, 60.0])
    assert_allclose(layout.pilot_amplitudes, [2.0, 1.0])
    assert layout.n_leds == 2


def test_reflectance_and_height_spread_round_trip() -> None:
    mapping = _mapping()
    mapping["room"]["reflectance"] = {"walls": 0.7, "floor": 0.2, "ceiling": 0.8}
    mapping["grid"]["receiver_height_sd"] = 0.05
    mapping["grid"]["receiver_tilt_sd"] = 4.0
    layout = layout_from_mapping(mapping)
    assert layout.room.reflectance == Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
    assert layout.grid.receiver_height_sd == 0.05
    assert layout.grid.receiver_tilt_sd == 4.0
    out = layout.to_mapping()
    assert out["room"]["reflectance"] == {"walls": 0.7, "floor": 0.2, "ceiling": 0.8}
    assert out["grid"]["receiver_height_sd"] == 0.05
    assert out["grid"]["receiver_tilt_sd"] == 4.0
    assert layout_from_mapping(out) == layout


def test_level_photodiodes_round_trip() -> None:
    mapping = _mapping()
    mapping["grid"]["receivers_level"] = True
    layout = layout_from_mapping(mapping)
    assert layout.grid.receivers_level is True
    out = layout.to_mapping()
    assert out["grid"]["receivers_level"] is True
    assert layout_from_mapping(out) == layout
    assert layout != layout_from_mapping(_mapping())


def test_absent_reflectance_and_spread_map_exactly_as_before() -> None:
    mapping = _mapping()
    mapping["room"]["reflectance"] = None
    mapping["grid"]["receiver_height_sd"] = 0.0
    mapping["grid"]["receiver_tilt_sd"] = 0.0
    mapping["grid"]["receivers_level"] = False
    layout = layout_from_mapping(mapping)
    assert layout.room.reflectance is None and layout.grid.receiver_height_sd == 0.0
    out = layout.to_mapping()
    assert set(out["room"]) == {"length", "width", "height"}
    assert set(out["grid"]) == {"step", "receiver_height"}
    assert layout == layout_from_mapping(_mapping())


@pytest.mark.parametrize(
    ("reflectance", "sd", "field"),
    [
        ({"walls": 1.0, "floor": 0.2, "ceiling": 0.8}, 0.0, "room.reflectance.walls"),
        ({"walls": 0.5, "floor": -0.1, "ceiling": 0.8}, 0.0, "room.reflectance.floor"),
        ({"walls": 0.5, "floor": 0.1, "ceiling": float("nan")}, 0.0, "room.reflectance.ceiling"),
        ({"walls": 0.5, "floor": 0.1}, 0.0, "room.reflectance.ceiling"),
        ({"walls": "shiny", "floor": 0.1, "ceiling": 0.1}, 0.0, "room.reflectance.walls"),
        ([0.5, 0.1, 0.1], 0.0, "room.reflectance"),
        (None, -0.05, "grid.receiver_height_sd"),
        (None, float("inf"), "grid.receiver_height_sd"),
    ],
    ids=[
        "walls-1",
        "floor-negative",
        "ceiling-nan",
        "ceiling-missing",
        "text",
        "list",
        "sd-negative",
        "sd-inf",
    ],
)
def test_reflectance_and_spread_validation_names_the_field(
    reflectance: Any, sd: float, field: str
) -> None:
    mapping = _mapping()
    mapping["room"]["reflectance"] = reflectance
    mapping["grid"]["receiver_height_sd"] = sd
    with pytest.raises(GeometryError) as info:
        layout_from_mapping(mapping)
    assert info.value.field == field


def test_reflectance_dataclass_checks_its_own_range() -> None:
    with pytest.raises(GeometryError) as info:
        Reflectance(walls=0.5, floor=0.2, ceiling=1.5)
    assert info.value.field == "room.reflectance.ceiling"
    with pytest.raises(GeometryError) as info:
        Grid(step=0.5, receiver_height=0.8, receiver_height_sd=-1.0)
    assert info.value.field == "grid.receiver_height_sd"


@pytest.mark.parametrize(
    ("name", "value"),
    [
        *(("receiver_tilt_sd", tilt_sd) for tilt_sd in (-1.0, 30.5, float("nan"), float("inf"))),
        # The level flag is a boolean only (not a number, not a word).
        *(("receivers_level", level) for level in (1, "yes", 0.0)),
    ],
)
def test_photodiode_fields_validation_names_the_field(name: str, value: object) -> None:
    mapping = _mapping()
    mapping["grid"][name] = value
    with pytest.raises(GeometryError) as info:
        layout_from_mapping(mapping)
    assert info.value.field == f"grid.{name}"


def test_level_photodiodes_with_a_tilt_spread_are_refused_naming_the_field() -> None:
    with pytest.raises(GeometryError, match="receiver_tilt_sd") as info:
        Grid(step=0.5, receiver_height=0.8, receiver_tilt_sd=4.0, receivers_level=True)
    assert info.value.field == "grid.receivers_level"
    assert Grid(step=0.5, receiver_height=0.8, receiver_tilt_sd=0.0, receivers_level=True)
