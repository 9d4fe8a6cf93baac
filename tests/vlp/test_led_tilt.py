"""Tilted LEDs: the layout's ``normal``, the channel with it, and its calibration.

Independent computations: the emission angle of a tilted LED is taken in the LED's own
rotated frame (a rotation that carries its normal to straight down, Rodrigues' formula),
never through the dot product the channel uses; gradients are checked against central
differences.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.schemas.calibrations import DEFAULT_LED_TILT_BOUND_DEG as SCHEMA_TILT_BOUND
from app.schemas.calibrations import MAX_LED_TILT_BOUND_DEG as SCHEMA_TILT_MAX
from app.vlp._calibration_fit import LedFit, led_rows
from app.vlp.calibration import (
    DEFAULT_LED_TILT_BOUND_DEG,
    MAX_LED_TILT_BOUND_DEG,
    Survey,
    calibrate,
    calibrated_layout,
    simulate_survey,
)
from app.vlp.channel import (
    channel_gain_gradients,
    channel_gains,
    led_constants,
    los_gain_gradients,
    los_gains,
)
from app.vlp.errors import GeometryError, MeasurementError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.presets import paper_layout
from app.vlp.reflections import diffuse_gains
from app.vlp.solvers.gridless.channel import ChannelKernel
from app.vlp.solvers.gridless.terminals import los_with_normal
from app.vlp.typing import FloatArray


def tilted_normal(tilt_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return (math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), -math.cos(t))


def with_tilts(layout: Layout, tilts: dict[int, tuple[float, float]]) -> Layout:
    """``layout`` with LED ``i`` tilted by ``tilts[i] = (tilt_deg, azimuth_deg)``."""
    leds = tuple(
        replace(led, normal=tilted_normal(*tilts[i])) if i in tilts else led
        for i, led in enumerate(layout.leds)
    )
    return replace(layout, leds=leds)


TILTS = {1: (12.0, 30.0), 4: (14.0, 200.0), 6: (5.0, 290.0), 11: (9.0, 110.0)}


@pytest.fixture(scope="module")
def tilted_room() -> Layout:
    return with_tilts(paper_layout(), TILTS)


def rotation_to_down(normal: FloatArray) -> FloatArray:
    """The rotation matrix carrying ``normal`` onto (0, 0, -1) (Rodrigues)."""
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(normal, down)
    sine, cosine = np.linalg.norm(axis), float(normal @ down)
    if sine < 1e-15:
        return np.eye(3)
    k = axis / sine
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.asarray(np.eye(3) + sine * cross + (1.0 - cosine) * cross @ cross)


def direct_tilted_gain(layout: Layout, i: int, receiver: FloatArray, up: FloatArray) -> float:
    """``h`` with the emission angle measured in LED ``i``'s own rotated frame."""
    led = layout.leds[i]
    orders, prefactors = led_constants(layout)
    to_rx = receiver - np.array([led.x, led.y, led.z])
    in_frame = rotation_to_down(np.array(led.normal)) @ to_rx  # the LED now points down
    d = float(np.linalg.norm(to_rx))
    cos_alpha = -in_frame[2] / d
    cos_phi = float(-to_rx @ up) / d
    fov = math.cos(math.radians(layout.receiver.fov_deg))
    if cos_alpha <= 0 or cos_phi < fov:
        return 0.0
    return float(prefactors[i] * cos_alpha ** orders[i] * cos_phi / d**2)


def test_layout_normalises_the_normal_and_maps_it_back() -> None:
    base = paper_layout().to_mapping()
    base["leds"][2]["normal"] = [0.3, 0.0, -3.0]
    layout = layout_from_mapping(base)
    assert_allclose(layout.leds[2].normal, np.array([0.1, 0.0, -1.0]) / math.sqrt(1.01))
    assert layout.leds[2].tilted and not layout.leds[0].tilted
    mapped = layout.to_mapping()
    assert "normal" not in mapped["leds"][0]  # straight down maps as before the field
    assert layout_from_mapping(mapped) == layout


@pytest.mark.parametrize("normal", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
def test_layout_refuses_normals_not_facing_down(normal: list[float]) -> None:
    base = paper_layout().to_mapping()
    base["leds"][3]["normal"] = normal
    with pytest.raises(GeometryError) as caught:
        layout_from_mapping(base)
    assert caught.value.field == "leds[3].normal"


def test_the_default_normal_changes_nothing() -> None:
    room = paper_layout()
    explicit = replace(room, leds=tuple(replace(led, normal=(0.0, 0.0, -1.0)) for led in room.leds))
    rng = np.random.default_rng(1)
    points = rng.uniform(0.0, 4.0, (30, 2))
    assert np.array_equal(channel_gains(explicit, points), channel_gains(room, points))
    kernel, reference = ChannelKernel(explicit, 0.3), ChannelKernel(room, 0.3)
    xs, ys, zs = points[:, 0], points[:, 1], rng.uniform(0.5, 1.2, 30)
    assert np.array_equal(kernel.gradients_xyz(xs, ys, zs), reference.gradients_xyz(xs, ys, zs))
    assert not kernel.has_tilt


def test_tilted_channel_matches_the_rotated_frame(tilted_room: Layout) -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(0.0, 4.0, (25, 2))
    gains = channel_gains(tilted_room, points)
    up = np.array([0.0, 0.0, 1.0])
    height = tilted_room.grid.receiver_height
    expected = np.array(
        [
            [direct_tilted_gain(tilted_room, i, np.array([*p, height]), up) for p in points]
            for i in range(tilted_room.n_leds)
        ]
    )
    assert_allclose(gains, expected, rtol=1e-12, atol=1e-300)
    # and the tilt matters: at least a few per cent on the tilted LEDs
    untilted = channel_gains(paper_layout(), points)
    assert np.max(np.abs(gains[4] / untilted[4] - 1.0)) > 0.05
    assert np.array_equal(gains[0], untilted[0])


def test_tilted_los_gains_match_the_rotated_frame(tilted_room: Layout) -> None:
    rng = np.random.default_rng(3)
    xyz = np.column_stack((rng.uniform(0.0, 4.0, (12, 2)), rng.uniform(0.3, 1.5, 12)))
    raw = np.column_stack((rng.uniform(-0.3, 0.3, (12, 2)), np.ones(12)))
    normals = raw / np.linalg.norm(raw, axis=1)[:, None]
    expected = np.array(
        [
            [direct_tilted_gain(tilted_room, i, xyz[k], normals[k]) for k in range(12)]
            for i in range(tilted_room.n_leds)
        ]
    )
    assert_allclose(los_gains(tilted_room, xyz, normals), expected, rtol=1e-12, atol=1e-300)


def _central(fun: object, at: FloatArray, step: float = 1e-6) -> FloatArray:
    columns = []
    for axis in range(at.shape[-1]):
        shift = np.zeros(at.shape[-1])
        shift[axis] = step
        columns.append((fun(at + shift) - fun(at - shift)) / (2 * step))  # type: ignore[operator]
    return np.stack(columns, axis=-1)


def test_tilted_gradients_match_finite_differences(tilted_room: Layout) -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(0.5, 3.5, (10, 2))
    _, flat = channel_gain_gradients(tilted_room, points)
    numeric = _central(lambda p: channel_gains(tilted_room, p), points)
    assert_allclose(flat, numeric, rtol=1e-5, atol=1e-9 * np.max(np.abs(flat)))
    xyz = np.column_stack((points, rng.uniform(0.4, 1.3, 10)))
    _, spatial = los_gain_gradients(tilted_room, xyz)
    numeric = _central(lambda p: los_gains(tilted_room, p), xyz)
    assert_allclose(spatial, numeric, rtol=1e-5, atol=1e-9 * np.max(np.abs(spatial)))


def test_solver_kernels_agree_with_the_channel(tilted_room: Layout) -> None:
    rng = np.random.default_rng(5)
    points = rng.uniform(0.0, 4.0, (15, 2))
    xs, ys = points[:, 0], points[:, 1]
    kernel = ChannelKernel(tilted_room, scale=2.0)
    pilots = tilted_room.pilot_amplitudes[:, None] / 2.0
    gains, gradients = channel_gain_gradients(tilted_room, points)
    assert_allclose(kernel.gains_xy(xs, ys), gains * pilots, rtol=1e-12)
    blocks = kernel.gradients_xy(xs, ys)
    n = len(xs)
    assert_allclose(blocks[:, :n], gradients[:, :, 0] * pilots, rtol=1e-10, atol=1e-300)
    assert_allclose(blocks[:, n : 2 * n], gradients[:, :, 1] * pilots, rtol=1e-10, atol=1e-300)
    zs = rng.uniform(0.4, 1.3, n)
    xyz = np.column_stack((points, zs))
    los, los_gradients = los_gain_gradients(tilted_room, xyz)
    blocks = kernel.gradients_xyz(xs, ys, zs)
    assert_allclose(blocks[:, 3 * n : 4 * n], los * pilots, rtol=1e-12)
    for axis in range(3):
        assert_allclose(
            blocks[:, axis * n : (axis + 1) * n],
            los_gradients[:, :, axis] * pilots,
            rtol=1e-10,
            atol=1e-12 * np.max(np.abs(los_gradients)),
        )
    normal = np.array([0.1, -0.2, 1.0]) / math.sqrt(1.05)
    raw = np.array([1.3, 2.2, 0.9])
    one, one_gradient = los_with_normal(ChannelKernel(tilted_room, 1.0), raw, normal)
    want, want_gradient = los_gain_gradients(tilted_room, raw[None, :], normal[None, :])
    pilot = tilted_room.pilot_amplitudes
    assert_allclose(one, want[:, 0] * pilot, rtol=1e-12)
    assert_allclose(one_gradient, want_gradient[:, 0, :] * pilot[:, None], rtol=1e-10, atol=1e-20)


def test_fingerprint_uses_the_tilted_channel(tilted_room: Layout) -> None:
    fingerprint = build_fingerprint(tilted_room)
    centres = tilted_room.cell_centres()
    assert_allclose(fingerprint.gains.toarray(), channel_gains(tilted_room, centres), rtol=1e-12)


def test_reflections_follow_the_leds_emission() -> None:
    room = paper_layout()
    room = replace(room, room=replace(room.room, reflectance=Reflectance(0.7, 0.2, 0.8)))
    xyz = np.array([[1.0, 1.2, 0.85], [3.0, 2.5, 0.85]])
    straight = diffuse_gains(room, xyz)
    # A barely tilted LED takes the unfactored quadrature: it must agree with the factored one.
    barely = with_tilts(room, {i: (1e-7, 0.0) for i in range(room.n_leds)})
    assert_allclose(diffuse_gains(barely, xyz), straight, rtol=1e-6)
    # An LED next to the wall x = 0 turned towards it lights that wall more.
    led = 4  # (0.5, 3.5)
    towards = diffuse_gains(with_tilts(room, {led: (25.0, 180.0)}), xyz)
    away = diffuse_gains(with_tilts(room, {led: (25.0, 0.0)}), xyz)
    assert towards[led, 0] > straight[led, 0] > away[led, 0]
    assert np.array_equal(towards[0], straight[0])


def survey_points(layout: Layout, step: float = 0.4) -> FloatArray:
    ticks_x = np.arange(0.2, layout.room.length, step)
    ticks_y = np.arange(0.2, layout.room.width, step)
    return np.array([(x, y) for x in ticks_x for y in ticks_y])


def test_calibration_recovers_a_known_tilt_with_noise(tilted_room: Layout) -> None:
    nominal = paper_layout()
    true = replace(
        tilted_room,
        leds=tuple(replace(led, half_power_angle_deg=55.0) for led in tilted_room.leds),
    )
    survey = simulate_survey(true, survey_points(true), 2e-8, rng=7)  # about 40 dB
    result = calibrate(nominal, survey)
    for i, (tilt, azimuth) in TILTS.items():
        assert result.tilts_deg[i] == pytest.approx(tilt, abs=1.0)
        if tilt >= 10:
            assert (result.tilt_azimuths_deg[i] - azimuth + 180) % 360 - 180 == pytest.approx(
                0.0, abs=5.0
            )
    level = [i for i in range(true.n_leds) if i not in TILTS]
    assert np.max(result.tilts_deg[level]) < 1.0
    assert_allclose(result.half_power_angles_deg, 55.0, atol=1.0)
    layout = calibrated_layout(nominal, result)
    assert_allclose(layout.led_normals, result.led_normals)
    # Without the tilt fit the same survey leaves the tilted LEDs' residuals far larger.
    kept = calibrate(nominal, survey, led_tilt_bound_deg=0.0)
    assert np.all(kept.tilts_deg == 0.0)
    assert kept.residual_rms_after[4] > 3 * result.residual_rms_after[4]


def test_tilt_stays_within_its_bound(tilted_room: Layout) -> None:
    survey = simulate_survey(tilted_room, survey_points(tilted_room), 1e-9, rng=8)
    result = calibrate(paper_layout(), survey, led_tilt_bound_deg=6.0)
    assert np.max(result.tilts_deg) <= 6.0 + 1e-9
    assert result.tilts_deg[4] == pytest.approx(6.0, abs=0.05)  # 14 degrees, held at 6


def test_tilt_bound_is_checked() -> None:
    room = paper_layout()
    survey = simulate_survey(room, survey_points(room), 0.0)
    for bad in (-1.0, 46.0, math.nan):
        with pytest.raises(MeasurementError) as caught:
            calibrate(room, survey, led_tilt_bound_deg=bad)
        assert caught.value.field == "led_tilt_bound_deg"
    assert SCHEMA_TILT_BOUND == DEFAULT_LED_TILT_BOUND_DEG
    assert SCHEMA_TILT_MAX == MAX_LED_TILT_BOUND_DEG


def test_censored_rows_hold_the_beam_where_nothing_was_detected() -> None:
    """Rows below the floor say "weak here": left out, the beam is fitted to the strong rows
    alone; censored, a model above the floor at those rows costs. Over seeds and LEDs the
    censored fit's half-power angles are closer to the truth."""
    room = paper_layout()
    true = replace(room, leds=tuple(replace(led, half_power_angle_deg=40.0) for led in room.leds))
    errors: dict[str, list[FloatArray]] = {"censored": [], "dropped": []}
    for seed in range(3):
        full = simulate_survey(true, survey_points(true), 3e-7, rng=seed)
        floor = float(np.quantile(full.amplitudes, 0.6))
        seen = full.amplitudes >= floor
        surveys = {
            "censored": Survey(
                full.points, full.led_indices, np.where(seen, full.amplitudes, np.nan), floor
            ),
            "dropped": Survey(full.points[seen], full.led_indices[seen], full.amplitudes[seen]),
        }
        for name, survey in surveys.items():
            fit = calibrate(room, survey, led_tilt_bound_deg=0.0)
            errors[name].append(np.abs(fit.half_power_angles_deg - 40.0))
    assert np.mean(errors["censored"]) < 0.9 * np.mean(errors["dropped"])


def test_a_censored_row_costs_only_its_excess_over_the_floor() -> None:
    room = paper_layout()
    points = np.array([[0.5, 0.5], [3.5, 3.5], [2.0, 2.0]])
    rows = led_rows(room, 0, points, np.array([np.nan, np.nan, 1.0]), floor=1e-6)
    fit = LedFit(1.0, 1.0, np.zeros(2), (True,) * 6)
    modelled = rows.model(1.0, 1.0, np.zeros(2), np.zeros(3))
    assert modelled[0] > 1e-6 > modelled[1]  # under the LED, and far from it
    residuals = rows.residuals(fit, np.zeros(3))
    assert residuals[0] == pytest.approx(modelled[0] - 1e-6) and residuals[1] == 0.0
    columns, _ = rows.residual_jacobian(fit, np.zeros(3))
    assert not columns[1].any() and columns[0].any()


def test_survey_refuses_rows_that_are_all_censored() -> None:
    with pytest.raises(MeasurementError) as caught:
        Survey(np.zeros((2, 2)), np.array([0, 1]), np.array([np.nan, np.nan]))
    assert caught.value.field == "amplitudes"
    with pytest.raises(MeasurementError):
        Survey(np.zeros((1, 2)), np.array([0]), np.array([np.inf]))


def test_simulator_tilts_leds_after_every_other_tolerance() -> None:
    from app.vlp.simulation import Impairments
    from app.vlp.simulation.terminals import _true_layout

    room = with_tilts(paper_layout(), {2: (7.0, 45.0)})
    base = Impairments(led_amplitude_sd=0.05, led_half_power_sd_deg=3.0, led_position_sd_m=0.02)
    plain = _true_layout(room, base, np.random.default_rng(4))
    tilted = _true_layout(room, replace(base, led_tilt_max_deg=10.0), np.random.default_rng(4))
    assert plain.leds[2].normal == room.leds[2].normal  # the layout's own tilt is kept
    assert_allclose(tilted.led_positions, plain.led_positions)
    assert_allclose(tilted.half_power_angles_deg, plain.half_power_angles_deg)
    turned = np.degrees(np.arccos(np.sum(tilted.led_normals * room.led_normals, axis=1)))
    assert np.all(turned <= 10.0 + 1e-9) and np.ptp(turned) > 3.0
    with pytest.raises(GeometryError):
        Impairments(led_tilt_max_deg=90.0)
