"""First-bounce diffuse reflections: energy, closed forms, an independent quadrature, tilt."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import dblquad

from app.vlp.channel import lambertian_order, los_gains
from app.vlp.errors import GeometryError
from app.vlp.layout import Grid, Layout, Led, Receiver, Reflectance, Room
from app.vlp.presets import paper_layout
from app.vlp.reflections import (
    SURFACES,
    diffuse_gains,
    surface_flux_fractions,
    view_factors,
)

WALLS_ONLY = Reflectance(walls=0.7, floor=0.0, ceiling=0.0)


def _corner_factor(side_a: float, side_b: float, distance: float) -> float:
    """Howell's catalogue: element parallel to a rectangle, normal through one corner."""
    x, y = side_a / distance, side_b / distance
    sx, sy = math.sqrt(1 + x * x), math.sqrt(1 + y * y)
    return (x / sx * math.atan(y / sx) + y / sy * math.atan(x / sy)) / (2 * math.pi)


def _parallel_factor(
    foot: tuple[float, float], extent: tuple[float, float], distance: float
) -> float:
    """Element parallel to a rectangle [0, a] x [0, b] over the foot point, by superposition."""
    total = 0.0
    for side_u in (foot[0], extent[0] - foot[0]):
        for side_v in (foot[1], extent[1] - foot[1]):
            if side_u > 0 and side_v > 0:
                total += _corner_factor(side_u, side_v, distance)
    return total


def _box(fov_deg: float = 70.0, leds: tuple[Led, ...] | None = None) -> Layout:
    return Layout(
        room=Room(4.0, 3.0, 2.5),
        grid=Grid(0.5, 0.8),
        leds=leds or (Led(1.3, 0.9, 2.5, 60.0), Led(3.8, 2.6, 2.2, 45.0), Led(0.05, 1.5, 2.4)),
        receiver=Receiver(area=1e-4, fov_deg=fov_deg),
    )


@pytest.mark.parametrize("led_index", [0, 1, 2], ids=["m1", "m2-low", "near-wall"])
def test_flux_on_all_surfaces_adds_up_to_one(led_index: int) -> None:
    fractions = surface_flux_fractions(_box(), led_index)
    assert set(fractions) == set(SURFACES)
    assert fractions["ceiling"] == 0.0  # a downward LED does not light the plane above it
    assert_allclose(sum(fractions.values()), 1.0, rtol=0, atol=2e-5)


def test_floor_flux_matches_the_configuration_factor() -> None:
    # A Lambertian (m = 1) point source's flux on a parallel rectangle is the differential
    # element-to-rectangle configuration factor.
    layout = _box()
    assert_allclose(float(lambertian_order(60.0)), 1.0)
    led = layout.leds[0]
    expected = _parallel_factor((led.x, led.y), (4.0, 3.0), led.z)
    assert_allclose(surface_flux_fractions(layout, 0)["floor"], expected, rtol=1e-6)


def test_view_factors_match_closed_form_and_close_the_box() -> None:
    layout = _box(fov_deg=90.0)
    facing_wall = view_factors(layout, np.array([0.3, 1.1, 0.7]), np.array([-1.0, 0.0, 0.0]))
    expected = _parallel_factor((1.1, 0.7), (3.0, 2.5), 0.3)
    assert_allclose(facing_wall["wall_x0"], expected, rtol=1e-6)
    for point in ([2.0, 1.5, 0.8], [0.02, 0.03, 0.5], [3.9, 2.9, 2.45]):
        factors = view_factors(layout, np.array(point))
        assert_allclose(sum(factors.values()), 1.0, rtol=0, atol=2e-4)


def _reference_gain(layout: Layout, led_index: int, point: np.ndarray, rho: Reflectance) -> float:
    """The two-hop integral for one LED and an upward receiver, by scipy's adaptive dblquad
    with the FOV boundary as exact integration limits (walls: downward LEDs light neither the
    ceiling nor, for an upward receiver, a visible part of the floor)."""
    led = layout.leds[led_index]
    source = np.array([led.x, led.y, led.z])
    m = float(lambertian_order(led.half_power_angle_deg))
    rx = layout.receiver
    optics = (
        rx.area * rx.filter_gain * rx.refractive_index**2 / math.sin(math.radians(rx.fov_deg)) ** 2
    )
    cot_fov = 1 / math.tan(math.radians(rx.fov_deg))
    length, width, height = layout.room.length, layout.room.width, layout.room.height

    def integrand(q: np.ndarray, normal: np.ndarray, reflectance: float) -> float:
        to_led, to_rx = source - q, point - q
        d1, d2 = float(np.linalg.norm(to_led)), float(np.linalg.norm(to_rx))
        cos_a1, cos_b1 = float(to_led[2]) / d1, float(normal @ to_led) / d1
        cos_b2, cos_p2 = float(normal @ to_rx) / d2, -float(to_rx[2]) / d2
        if min(cos_a1, cos_b1, cos_b2, cos_p2) <= 0:
            return 0.0
        first = (m + 1) / (2 * math.pi * d1 * d1) * cos_a1**m * cos_b1
        return float(first * reflectance * cos_b2 * cos_p2 * optics / (math.pi * d2 * d2))

    total = 0.0
    walls = [  # (normal, point on wall from (u, z), u range, receiver's distance, its u)
        (np.array([1.0, 0, 0]), lambda u, z: np.array([0.0, u, z]), width, point[0], point[1]),
        (
            np.array([-1.0, 0, 0]),
            lambda u, z: np.array([length, u, z]),
            width,
            length - point[0],
            point[1],
        ),
        (np.array([0, 1.0, 0]), lambda u, z: np.array([u, 0.0, z]), length, point[1], point[0]),
        (
            np.array([0, -1.0, 0]),
            lambda u, z: np.array([u, width, z]),
            length,
            width - point[1],
            point[0],
        ),
    ]
    for normal, at, extent, distance, foot in walls:
        value, _ = dblquad(
            lambda z, u, n=normal, at=at: integrand(at(u, z), n, rho.walls),
            0.0,
            extent,
            lambda u, d=distance, f=foot: min(height, point[2] + cot_fov * math.hypot(d, u - f)),
            height,
            epsabs=0,
            epsrel=1e-7,
        )
        total += value
    return total


@pytest.mark.parametrize(
    "point",
    [[0.1, 0.1, 0.85], [0.1, 1.9, 0.85], [2.0, 1.7, 0.85], [0.01, 1.2, 0.85]],
    ids=["corner", "wall", "centre", "at-wall"],
)
def test_diffuse_gains_match_an_independent_quadrature(point: list[float]) -> None:
    layout = paper_layout()
    xyz = np.array([point])
    gains = diffuse_gains(layout, xyz, reflectance=WALLS_ONLY)
    for led_index in (0, 5, 15):
        expected = _reference_gain(layout, led_index, xyz[0], WALLS_ONLY)
        assert_allclose(gains[led_index, 0], expected, rtol=1e-3)


def test_hanging_leds_match_an_independent_quadrature() -> None:
    # LEDs below the ceiling: a wall is lit only below the LED's height and seen only above
    # the FOV edge, a thin band that needs finer cells than the default
    # (docs/explanation/reflections.md).
    # The ceiling stays dark: the LEDs point down.
    layout = _box(leds=(Led(1.3, 0.9, 2.0, 60.0), Led(3.0, 2.0, 1.8, 40.0)))
    rho = Reflectance(walls=0.6, floor=0.3, ceiling=0.8)
    xyz = np.array([[1.0, 1.2, 0.8]])
    gains = diffuse_gains(layout, xyz, reflectance=rho, element_size_m=0.1)
    only_ceiling = diffuse_gains(layout, xyz, reflectance=Reflectance(0.0, 0.0, 0.8))
    assert np.all(only_ceiling == 0)
    for led_index in (0, 1):
        expected = _reference_gain(layout, led_index, xyz[0], rho)
        assert_allclose(gains[led_index, 0], expected, rtol=5e-3)


def test_converges_with_element_size() -> None:
    layout = paper_layout()
    xyz = np.array([[0.1, 0.1, 0.85], [0.3, 2.1, 0.85], [2.0, 2.0, 0.85]])
    finest = diffuse_gains(layout, xyz, reflectance=WALLS_ONLY, element_size_m=0.03)
    errors = []
    for size in (0.5, 0.25, 0.1):
        gains = diffuse_gains(layout, xyz, reflectance=WALLS_ONLY, element_size_m=size)
        errors.append(float(np.max(np.abs(gains - finest) / finest.max(axis=0))))
    assert errors[1] < 5e-3 and errors[2] < 3e-3
    assert errors[2] <= errors[0]


def test_paper_room_reflects_a_quarter_of_its_light() -> None:
    # As independent simulators of the same room give: walls 0.7, NLoS/LoS about 25 % over the
    # grid.
    layout = paper_layout()
    centres = layout.cell_centres()[::7]
    xyz = np.column_stack((centres, np.full(len(centres), 0.85)))
    ratio = diffuse_gains(layout, xyz, reflectance=WALLS_ONLY).sum(0) / los_gains(layout, xyz).sum(
        0
    )
    assert 0.22 < float(ratio.mean()) < 0.28


def test_tilting_towards_a_wall_sees_more_of_it() -> None:
    layout = paper_layout()
    xyz = np.tile([0.4, 2.0, 0.85], (3, 1))
    tilt = math.radians(30)
    normals = np.array(
        [[0, 0, 1.0], [-math.sin(tilt), 0, math.cos(tilt)], [math.sin(tilt), 0, math.cos(tilt)]]
    )
    reflecting = Layout(
        room=Room(4.0, 4.0, 3.0, reflectance=WALLS_ONLY),
        grid=layout.grid,
        leds=layout.leds,
        receiver=layout.receiver,
    )
    total = diffuse_gains(reflecting, xyz, normals).sum(axis=0)
    upright, towards, away = total
    # (every wall reflects: tilting away from x = 0 turns towards x = 4, hence the small drop)
    assert towards > 1.05 * upright and upright > away


def test_floor_seen_only_by_a_receiver_tilted_past_the_horizon() -> None:
    layout = _box()
    floor_only = Reflectance(walls=0.0, floor=0.5, ceiling=0.0)
    xyz = np.tile([2.0, 1.5, 1.0], (2, 1))
    tilt = math.radians(60)
    normals = np.array([[0, 0, 1.0], [math.sin(tilt), 0, math.cos(tilt)]])
    gains = diffuse_gains(layout, xyz, normals, reflectance=floor_only)
    assert np.all(gains[:, 0] == 0)  # FOV 70 + tilt 0 < 90: the floor is out of view
    # FOV 70 + tilt 60: it sees the floor from 40 degrees below the horizon, x > 3.19 m
    assert np.all(gains[:, 1] > 0)


def test_reflectance_source_and_zero_case() -> None:
    layout = paper_layout()
    xyz = np.array([[1.0, 1.0, 0.85]])
    assert np.all(diffuse_gains(layout, xyz) == 0)
    reflecting = Layout(
        room=Room(4.0, 4.0, 3.0, reflectance=Reflectance(0.35, 0.0, 0.0)),
        grid=layout.grid,
        leds=layout.leds,
        receiver=layout.receiver,
    )
    from_layout = diffuse_gains(reflecting, xyz)
    overridden = diffuse_gains(reflecting, xyz, reflectance=WALLS_ONLY)
    assert_allclose(overridden, 2 * from_layout, rtol=1e-12)  # linear in the reflectance


def test_bad_inputs_name_the_field() -> None:
    layout = paper_layout()
    with pytest.raises(GeometryError) as info:
        diffuse_gains(layout, np.array([[5.0, 1.0, 0.85]]), reflectance=WALLS_ONLY)
    assert info.value.field == "points"
    with pytest.raises(GeometryError) as info:
        diffuse_gains(layout, np.array([[1.0, 1.0, 0.85]]), element_size_m=0.0)
    assert info.value.field == "element_size_m"
    with pytest.raises(GeometryError) as info:
        surface_flux_fractions(layout, 16)
    assert info.value.field == "led_index"
