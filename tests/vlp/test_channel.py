"""Channel model: anchor values computed by hand, the API formula, and the gradient."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.channel import (
    channel_gain_gradients,
    channel_gains,
    concentrator_gain,
    lambertian_order,
    led_constants,
    los_gain_gradients,
    los_gains,
)
from app.vlp.errors import GeometryError
from app.vlp.layout import Layout

from .conftest import anchor_layout, direct_gain


@pytest.mark.parametrize(
    ("angle_deg", "expected"),
    [(70.0, 0.646059), (60.0, 1.0), (12.5, 28.89)],
    ids=["70deg", "60deg", "12.5deg"],
)
def test_lambertian_order_anchors(angle_deg: float, expected: float) -> None:
    assert_allclose(lambertian_order(angle_deg), expected, rtol=2e-4)


def test_lambertian_order_vectorised_and_half_power() -> None:
    angles = np.array([15.0, 45.0, 80.0])
    orders = lambertian_order(angles)
    # by definition cos(angle)^m = 1/2
    assert_allclose(np.cos(np.radians(angles)) ** orders, 0.5, rtol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 90.0, -5.0, float("nan")], ids=str)
def test_lambertian_order_rejects_bad_angles(angle: float) -> None:
    with pytest.raises(GeometryError):
        lambertian_order(angle)


def test_concentrator_gain() -> None:
    assert_allclose(concentrator_gain(1.5, 60.0), 3.0, rtol=1e-12)
    assert_allclose(concentrator_gain(1.0, 90.0), 1.0, rtol=1e-12)
    with pytest.raises(GeometryError) as info:
        concentrator_gain(1.5, 0.0)
    assert info.value.field == "fov_deg"


@pytest.mark.parametrize(
    ("offset", "expected", "incidence_deg"),
    [
        ((0.0, 0.0), 1.700238e-5, 0.0),
        ((1.25, 1.25), 6.631813e-6, 39.43),
        ((3.75, 1.25), 0.0, 61.46),
    ],
    ids=["below", "offset-in-fov", "outside-fov"],
)
def test_gain_anchors(offset: tuple[float, float], expected: float, incidence_deg: float) -> None:
    layout = anchor_layout()
    point = np.array([[0.5 + offset[0], 0.5 + offset[1]]])
    gain = channel_gains(layout, point)
    assert gain.shape == (1, 1)
    assert_allclose(gain[0, 0], expected, rtol=1e-6, atol=1e-16)
    horizontal = float(np.hypot(*offset))
    assert_allclose(np.degrees(np.arctan2(horizontal, 2.15)), incidence_deg, atol=0.01)


def test_gains_match_api_formula(mixed_room: Layout, rng: np.random.Generator) -> None:
    points = rng.uniform(0, 1, size=(40, 2)) * [mixed_room.room.length, mixed_room.room.width]
    gains = channel_gains(mixed_room, points)
    expected = np.array(
        [
            [direct_gain(mixed_room, i, (p[0], p[1])) for p in points]
            for i in range(mixed_room.n_leds)
        ]
    )
    assert gains.shape == (mixed_room.n_leds, 40)
    assert np.any(expected == 0) and np.any(expected > 0)
    assert_allclose(gains, expected, rtol=1e-12, atol=0)


def test_led_constants(mixed_room: Layout) -> None:
    orders, prefactors = led_constants(mixed_room)
    rx = mixed_room.receiver
    assert_allclose(orders, lambertian_order(mixed_room.half_power_angles_deg))
    assert_allclose(
        prefactors,
        (orders + 1)
        * rx.area
        * rx.filter_gain
        * concentrator_gain(rx.refractive_index, rx.fov_deg)
        / (2 * np.pi),
    )


def test_gradient_matches_finite_differences(mixed_room: Layout, rng: np.random.Generator) -> None:
    points = rng.uniform(0.2, 0.8, size=(25, 2)) * [mixed_room.room.length, mixed_room.room.width]
    gains, grads = channel_gain_gradients(mixed_room, points)
    assert grads.shape == (mixed_room.n_leds, 25, 2)
    assert_allclose(gains, channel_gains(mixed_room, points))
    step = 1e-6
    for axis in range(2):
        shift = np.zeros(2)
        shift[axis] = step
        numeric = (
            channel_gains(mixed_room, points + shift) - channel_gains(mixed_room, points - shift)
        ) / (2 * step)
        # skip pairs straddling the FOV edge (the gain jumps there)
        smooth = (channel_gains(mixed_room, points + shift) > 0) == (
            channel_gains(mixed_room, points - shift) > 0
        )
        assert smooth.mean() > 0.9
        assert_allclose(
            grads[:, :, axis][smooth],
            numeric[smooth],
            rtol=1e-5,
            atol=1e-9 * float(np.max(np.abs(numeric))),
        )


def _tilted_normals(rng: np.random.Generator, count: int, max_deg: float) -> np.ndarray:
    polar = np.radians(rng.uniform(0, max_deg, count))
    azimuth = rng.uniform(0, 2 * np.pi, count)
    return np.column_stack(
        (np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar))
    )


def test_los_gains_equal_channel_gains_for_upward_receivers(
    mixed_room: Layout, rng: np.random.Generator
) -> None:
    points = rng.uniform(0, 1, size=(40, 2)) * [mixed_room.room.length, mixed_room.room.width]
    xyz = np.column_stack((points, np.full(40, mixed_room.grid.receiver_height)))
    expected = channel_gains(mixed_room, points)
    assert_allclose(los_gains(mixed_room, xyz), expected, rtol=1e-12, atol=0)
    upward = np.tile([0.0, 0.0, 1.0], (40, 1))
    assert_allclose(los_gains(mixed_room, xyz, upward), expected, rtol=1e-12, atol=0)


def test_los_gains_match_explicit_angles(mixed_room: Layout, rng: np.random.Generator) -> None:
    xyz = rng.uniform(0, 1, size=(30, 3)) * [3.0, 2.0, 1.5]
    normals = _tilted_normals(rng, 30, 40.0)
    gains = los_gains(mixed_room, xyz, normals)
    rx = mixed_room.receiver
    g_conc = rx.refractive_index**2 / np.sin(np.radians(rx.fov_deg)) ** 2
    for i, led in enumerate(mixed_room.leds):
        m = float(lambertian_order(led.half_power_angle_deg))
        for p in range(30):
            to_led = np.array([led.x, led.y, led.z]) - xyz[p]
            d = float(np.linalg.norm(to_led))
            irradiance = np.arccos(to_led[2] / d)
            incidence = np.arccos(float(normals[p] @ to_led) / d)
            seen = np.degrees(incidence) <= rx.fov_deg and np.degrees(irradiance) < 90
            expected = (
                (m + 1)
                / (2 * np.pi * d * d)
                * np.cos(irradiance) ** m
                * rx.area
                * rx.filter_gain
                * g_conc
                * np.cos(incidence)
                if seen
                else 0.0
            )
            assert_allclose(gains[i, p], expected, rtol=1e-10, atol=0)
    assert np.any(gains == 0) and np.any(gains > 0)


def test_los_gain_gradients_match_finite_differences(
    mixed_room: Layout, rng: np.random.Generator
) -> None:
    xyz = rng.uniform(0.2, 0.8, size=(25, 3)) * [3.0, 2.0, 1.5]
    normals = _tilted_normals(rng, 25, 30.0)
    gains, grads = los_gain_gradients(mixed_room, xyz, normals)
    assert grads.shape == (mixed_room.n_leds, 25, 3)
    assert_allclose(gains, los_gains(mixed_room, xyz, normals))
    step = 1e-6
    for axis in range(3):
        shift = np.zeros(3)
        shift[axis] = step
        ahead = los_gains(mixed_room, xyz + shift, normals)
        behind = los_gains(mixed_room, xyz - shift, normals)
        smooth = (ahead > 0) == (behind > 0)  # the gain jumps at the FOV edge
        assert smooth.mean() > 0.8
        assert_allclose(
            grads[:, :, axis][smooth],
            ((ahead - behind) / (2 * step))[smooth],
            rtol=1e-5,
            atol=1e-9 * float(np.max(np.abs(grads))),
        )


def test_los_gain_gradients_reduce_to_the_flat_ones(
    mixed_room: Layout, rng: np.random.Generator
) -> None:
    points = rng.uniform(0.2, 0.8, size=(20, 2)) * [3.0, 2.0]
    xyz = np.column_stack((points, np.full(20, mixed_room.grid.receiver_height)))
    _, flat = channel_gain_gradients(mixed_room, points)
    _, full = los_gain_gradients(mixed_room, xyz)
    assert_allclose(full[:, :, :2], flat, rtol=1e-10, atol=1e-20)


def test_los_gains_reject_bad_normals(mixed_room: Layout) -> None:
    with pytest.raises(GeometryError) as info:
        los_gains(mixed_room, np.array([[1.0, 1.0, 0.8]]), np.array([[0.0, 0.0, 2.0]]))
    assert info.value.field == "normals"
