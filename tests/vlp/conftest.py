"""Fixtures and factories for the science-core tests."""

from __future__ import annotations

import numpy as np
import pytest

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room


def anchor_layout() -> Layout:
    """One LED (half-power 70 deg) 2.15 m above the receivers, FOV 60 deg, 1 cm^2, n = 1.5."""
    return Layout(
        room=Room(length=5.0, width=5.0, height=3.0),
        grid=Grid(step=0.5, receiver_height=0.85),
        leds=(Led(x=0.5, y=0.5, z=3.0, half_power_angle_deg=70.0),),
        receiver=Receiver(area=1e-4, fov_deg=60.0, filter_gain=1.0, refractive_index=1.5),
    )


def mixed_layout() -> Layout:
    """A non-square room whose LEDs differ in height, beam and pilot, with a narrow FOV.

    3 m x 2 m, 0.25 m grid (12 x 8 = 96 points), 5 LEDs; with a 40 deg FOV many
    LED/point pairs are out of view, so H is genuinely sparse.
    """
    leds = (
        Led(x=0.4, y=0.3, z=2.8, half_power_angle_deg=60.0, pilot_amplitude=1.0),
        Led(x=2.6, y=0.5, z=2.5, half_power_angle_deg=45.0, pilot_amplitude=0.7),
        Led(x=1.5, y=1.0, z=3.0, half_power_angle_deg=30.0, pilot_amplitude=1.6),
        Led(x=0.7, y=1.8, z=2.2, half_power_angle_deg=70.0, pilot_amplitude=1.2),
        Led(x=2.9, y=1.9, z=2.9, half_power_angle_deg=55.0, pilot_amplitude=0.9),
    )
    return Layout(
        room=Room(length=3.0, width=2.0, height=3.0),
        grid=Grid(step=0.25, receiver_height=0.8),
        leds=leds,
        receiver=Receiver(area=2e-4, fov_deg=40.0, filter_gain=0.9, refractive_index=1.4),
        name="mixed",
    )


@pytest.fixture(scope="session")
def mixed_room() -> Layout:
    """See :func:`mixed_layout`."""
    return mixed_layout()


@pytest.fixture(scope="session")
def mixed_fingerprint(mixed_room: Layout) -> Fingerprint:
    """Fingerprint of :func:`mixed_layout` (read-only)."""
    return build_fingerprint(mixed_room)


def direct_gain(layout: Layout, led_index: int, point: tuple[float, float]) -> float:
    """``h_ij`` from the Lambertian LoS formula with explicit angles (no dz/d shortcut)."""
    led = layout.leds[led_index]
    rx = layout.receiver
    dx, dy = point[0] - led.x, point[1] - led.y
    dz = led.z - layout.grid.receiver_height
    d = float(np.sqrt(dx * dx + dy * dy + dz * dz))
    irradiance = float(np.arccos(dz / d))  # angle from the LED's downward axis
    incidence = float(np.arccos(dz / d))  # angle from the detector's upward axis
    if np.degrees(incidence) > rx.fov_deg:
        return 0.0
    m = -np.log(2.0) / np.log(np.cos(np.radians(led.half_power_angle_deg)))
    g_conc = rx.refractive_index**2 / np.sin(np.radians(rx.fov_deg)) ** 2
    return float(
        (m + 1)
        / (2 * np.pi * d * d)
        * np.cos(irradiance) ** m
        * rx.area
        * rx.filter_gain
        * g_conc
        * np.cos(incidence)
    )
