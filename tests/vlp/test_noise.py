"""Receiver noise model against a hand computation of Komine and Nakagawa's formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.vlp.channel import channel_gains
from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout
from app.vlp.noise import amplitude_noise_std, received_power_w, receiver_noise_variance


def _by_hand(power_w: float, area_cm2: float) -> float:
    """The same formulas with every constant typed out (area already in cm^2)."""
    q = 1.602176634e-19
    k = 1.380649e-23
    bandwidth = 1e8
    shot = 2 * q * 0.53 * power_w * bandwidth + 2 * q * 5100e-6 * 0.562 * bandwidth
    capacitance_f = 112e-12 * area_cm2
    thermal1 = 8 * math.pi * k * 295 / 10 * capacitance_f * 0.562 * bandwidth**2
    thermal2 = 16 * math.pi**2 * k * 295 * 1.5 / 30e-3 * capacitance_f**2 * 0.0868 * bandwidth**3
    return shot + thermal1 + thermal2


@pytest.mark.parametrize("power_w", [0.0, 1e-6, 1e-4], ids=["dark", "1uW", "100uW"])
@pytest.mark.parametrize("area_m2", [1e-4, 4e-5], ids=["1cm2", "0.4cm2"])
def test_variance_matches_hand_computation(power_w: float, area_m2: float) -> None:
    expected = _by_hand(power_w, area_m2 * 1e4)
    assert receiver_noise_variance(power_w, area_m2) == pytest.approx(expected, rel=1e-12)


def test_known_magnitudes_for_one_square_centimetre() -> None:
    # Background shot noise 9.18e-14 A^2, thermal 6.44e-15 + 3.50e-14 A^2 (1 cm^2, 112 pF).
    dark = receiver_noise_variance(0.0, 1e-4)
    assert dark == pytest.approx(9.1843e-14 + 6.4432e-15 + 3.5015e-14, rel=1e-4)
    # Each extra watt adds 2 q gamma B of shot noise.
    slope = receiver_noise_variance(1.0, 1e-4) - dark
    assert slope == pytest.approx(2 * 1.602176634e-19 * 0.53 * 1e8, rel=1e-9)


def test_amplitude_std_refers_current_to_pilot_units() -> None:
    variance = receiver_noise_variance(1e-5, 1e-4)
    std = amplitude_noise_std(1e-5, 1e-4, transmit_power_w=2.0)
    assert std == pytest.approx(math.sqrt(variance) / (0.53 * 2.0), rel=1e-12)
    # Keywords reach the receiver model.
    wide = amplitude_noise_std(1e-5, 1e-4, bandwidth_hz=2e8)
    assert wide > amplitude_noise_std(1e-5, 1e-4)


def test_received_power_sums_the_links(paper_room: Layout) -> None:
    point = np.array([1.3, 2.7])
    gains = channel_gains(paper_room, point[None, :])[:, 0]
    expected = 3.0 * float(np.sum(gains * paper_room.pilot_amplitudes))
    assert received_power_w(paper_room, point, transmit_power_w=3.0) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"received_power_w": -1.0, "area_m2": 1e-4}, "received_power_w"),
        ({"received_power_w": 0.0, "area_m2": 0.0}, "area_m2"),
        ({"received_power_w": math.nan, "area_m2": 1e-4}, "received_power_w"),
    ],
    ids=["negative-power", "zero-area", "nan-power"],
)
def test_bad_arguments_name_the_field(kwargs: dict[str, float], field: str) -> None:
    with pytest.raises(MeasurementError) as info:
        receiver_noise_variance(**kwargs)
    assert info.value.field == field
