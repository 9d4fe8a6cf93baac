"""The realistic simulator: the ideal case is the paper's, each impairment does what it says."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.channel import los_gains
from app.vlp.errors import GeometryError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.presets import paper_layout
from app.vlp.reflections import diffuse_gains
from app.vlp.simulation import (
    TRUE_ELEMENT_SIZE_M,
    Impairments,
    noise_std_for_snr,
    noisy_amplitudes,
    random_positions,
    simulate_terminals,
)

NOISELESS = math.inf


@pytest.fixture(scope="module")
def paper() -> Layout:
    return paper_layout()


def _positions(layout: Layout, count: int = 5, seed: int = 3) -> np.ndarray:
    return random_positions(layout, count, rng=seed)


def test_ideal_reproduces_noisy_amplitudes_exactly(paper: Layout) -> None:
    positions = _positions(paper)
    std = noise_std_for_snr(build_fingerprint(paper), 30.0)
    simulated = simulate_terminals(
        paper, positions, Impairments.ideal(), snr_db=30.0, rng=np.random.default_rng(7)
    )
    expected = noisy_amplitudes(paper, positions, std, rng=np.random.default_rng(7))
    assert simulated.amplitudes.tobytes() == expected.tobytes()
    assert simulated.noise_std == std
    assert_array_equal(simulated.gains, 1.0)
    assert_array_equal(simulated.heights, paper.grid.receiver_height)
    assert_array_equal(simulated.normals, np.tile([0.0, 0.0, 1.0], (5, 1)))
    assert simulated.true_layout == paper


def test_snr_means_the_same_noise_whatever_the_layout_says(paper: Layout) -> None:
    reflecting = dataclasses.replace(
        paper, room=dataclasses.replace(paper.room, reflectance=Reflectance(0.7, 0.2, 0.8))
    )
    positions = _positions(paper, 2)
    plain = simulate_terminals(paper, positions, Impairments.reflections(), snr_db=25.0, rng=1)
    told = simulate_terminals(reflecting, positions, Impairments.reflections(), snr_db=25.0, rng=1)
    assert plain.noise_std == told.noise_std
    assert_array_equal(plain.amplitudes, told.amplitudes)  # the truth ignores the layout's claim


def test_tilted_and_raised_receivers_see_los_gains_with_their_normals(paper: Layout) -> None:
    impairments = Impairments(height_sd_m=0.15, tilt_max_deg=20.0)
    positions = _positions(paper, 6)
    sim = simulate_terminals(paper, positions, impairments, snr_db=NOISELESS, rng=4)
    tilt = np.degrees(np.arccos(sim.normals[:, 2]))
    assert np.all(tilt <= 20.0) and np.ptp(tilt) > 1.0
    assert_allclose(np.linalg.norm(sim.normals, axis=1), 1.0)
    assert np.std(sim.heights) > 0.01
    xyz = np.column_stack((positions, sim.heights))
    expected = (los_gains(paper, xyz, sim.normals) * paper.pilot_amplitudes[:, None]).T
    assert_allclose(sim.amplitudes, expected, rtol=1e-12)


def test_the_tilt_component_sd_is_that_of_the_drawn_normals(paper: Layout) -> None:
    # The layout's receiver_tilt_sd a tilt range corresponds to: each component of the tilt
    # vector (polar angle times the azimuth's cosine, sine), from the simulator's own draws.
    impairments = Impairments.tilts(20.0)
    room = paper.room
    positions = np.random.default_rng(5).uniform((0, 0), (room.length, room.width), (4000, 2))
    sim = simulate_terminals(paper, positions, impairments, snr_db=NOISELESS, rng=6)
    polar = np.degrees(np.arccos(sim.normals[:, 2]))
    azimuth = np.arctan2(sim.normals[:, 1], sim.normals[:, 0])
    components = np.concatenate((polar * np.cos(azimuth), polar * np.sin(azimuth)))
    # 8000 components: the sample sd is within 2 % of the true one (about 1 % sd).
    assert math.sqrt(np.mean(components**2)) == pytest.approx(
        impairments.tilt_component_sd_deg, rel=0.02
    )
    assert Impairments().tilt_component_sd_deg == 0.0


def test_terminal_gains_and_the_common_scale_multiply(paper: Layout) -> None:
    positions = _positions(paper, 40)
    ideal = simulate_terminals(paper, positions, Impairments(), snr_db=NOISELESS, rng=2)
    spread = simulate_terminals(
        paper, positions, Impairments(gain_sd=0.1, common_scale=1.3), snr_db=NOISELESS, rng=2
    )
    assert_allclose(spread.amplitudes, 1.3 * spread.gains[:, None] * ideal.amplitudes, rtol=1e-12)
    assert 0.05 < float(np.std(spread.gains)) < 0.15
    assert np.all(spread.gains > 0)


def test_reflections_add_exactly_the_fine_diffuse_gains(paper: Layout) -> None:
    positions = _positions(paper, 3)
    rho = Reflectance(0.7, 0.2, 0.8)
    ideal = simulate_terminals(paper, positions, Impairments(), snr_db=NOISELESS, rng=0)
    lit = simulate_terminals(
        paper, positions, Impairments(reflectance=rho), snr_db=NOISELESS, rng=0
    )
    xyz = np.column_stack((positions, np.full(3, paper.grid.receiver_height)))
    diffuse = diffuse_gains(paper, xyz, reflectance=rho, element_size_m=TRUE_ELEMENT_SIZE_M)
    assert_allclose(lit.amplitudes - ideal.amplitudes, diffuse.T, rtol=1e-9)
    assert lit.true_layout.room.reflectance == rho


def test_led_tolerances_perturb_the_true_layout_only(paper: Layout) -> None:
    positions = _positions(paper, 4)
    impairments = Impairments(
        led_amplitude_sd=0.05, led_half_power_sd_deg=3.0, led_position_sd_m=0.05
    )
    sim = simulate_terminals(paper, positions, impairments, snr_db=NOISELESS, rng=9)
    true = sim.true_layout
    assert 0.01 < float(np.std(true.pilot_amplitudes)) < 0.1
    assert 0.5 < float(np.std(true.half_power_angles_deg - 60.0)) < 6.0
    shift = true.led_positions - paper.led_positions
    assert np.all(shift[:, 2] == 0) and 0.01 < float(np.std(shift[:, :2])) < 0.1
    xyz = np.column_stack((positions, np.full(4, paper.grid.receiver_height)))
    expected = (los_gains(true, xyz) * true.pilot_amplitudes[:, None]).T
    assert_allclose(sim.amplitudes, expected, rtol=1e-12)


def test_named_conditions() -> None:
    assert Impairments.ideal().is_ideal
    assert Impairments.reflections(0.7).reflectance == Reflectance(0.7, 0.0, 0.0)
    assert Impairments.gain_spread(0.1).gain_sd == 0.1
    assert Impairments.heights(0.15).height_sd_m == 0.15
    assert Impairments.tilts(20).tilt_max_deg == 20
    led = Impairments.led_tolerances(0.05, 3.0)
    assert (led.led_amplitude_sd, led.led_half_power_sd_deg) == (0.05, 3.0)
    mix = Impairments.realistic_mix()
    assert mix.reflectance == Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
    assert (mix.tilt_max_deg, mix.height_sd_m) == (10.0, 0.05)
    assert (mix.led_amplitude_sd, mix.led_half_power_sd_deg) == (0.05, 3.0)
    assert not mix.is_ideal


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: Impairments(gain_sd=-0.1), "impairments.gain_sd"),
        (lambda: Impairments(tilt_max_deg=95.0), "impairments.tilt_max_deg"),
        (lambda: Impairments(height_sd_m=math.nan), "impairments.height_sd_m"),
        (lambda: Impairments(common_scale=0.0), "impairments.common_scale"),
    ],
    ids=["gain", "tilt", "height", "scale"],
)
def test_bad_impairments_name_the_field(make: Callable[[], Impairments], field: str) -> None:
    with pytest.raises(GeometryError) as info:
        make()
    assert info.value.field == field
