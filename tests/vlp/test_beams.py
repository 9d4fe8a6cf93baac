"""Tabulated LED beams: the table, its interpolant, and the channel that uses it.

The reference computations are independent of the code under test: the Lambertian
``cos^m`` formula written out here, finite differences of the gains, ``scipy.integrate``
quadrature of the interpolant, and the closed box's energy balance.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import integrate

from app.vlp.beams import Beam, beam_arrays, evaluate_beams
from app.vlp.channel import (
    channel_gain_gradients,
    channel_gains,
    lambertian_order,
    los_gain_gradients,
    los_gains,
)
from app.vlp.errors import GeometryError
from app.vlp.layout import Layout
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.presets import paper_layout
from app.vlp.reflections import diffuse_gains, surface_flux_fractions
from app.vlp.solvers.gridless.channel import ChannelKernel

BATWING = Beam((0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0), (1.0, 1.05, 1.12, 1.1, 0.7, 0.3, 0.05))


def _with_beams(layout: Layout, beam: Beam, *, tilt_every_other: bool = False) -> Layout:
    leds = []
    for i, led in enumerate(layout.leds):
        normal = (0.15, -0.1 * (i % 3), -1.0) if tilt_every_other and i % 2 else led.normal
        leds.append(replace(led, beam=beam, normal=normal))
    return replace(layout, leds=tuple(leds))


def _lambertian_gains(layout: Layout, points: np.ndarray, order: float) -> np.ndarray:
    """Paper eq. 1 written out for LEDs pointing down over upward receivers."""
    rx = layout.receiver
    concentrator = rx.refractive_index**2 / math.sin(math.radians(rx.fov_deg)) ** 2
    leds = layout.led_positions
    dz = leds[:, 2] - layout.grid.receiver_height
    d2 = ((points[None, :, :] - leds[:, None, :2]) ** 2).sum(-1) + dz[:, None] ** 2
    cos = dz[:, None] / np.sqrt(d2)
    gains = (order + 1) / (2 * math.pi * d2) * cos**order * rx.area * rx.filter_gain
    gains = gains * concentrator * cos
    return np.where(cos >= math.cos(math.radians(rx.fov_deg)), gains, 0.0)


@pytest.mark.parametrize(
    ("angles", "values", "field"),
    [
        ((0.0,), (1.0,), "angles_deg"),
        ((1.0, 30.0), (1.0, 1.0), "angles_deg"),
        ((0.0, 30.0, 30.0), (1.0, 1.0, 1.0), "angles_deg"),
        ((0.0, 91.0), (1.0, 1.0), "angles_deg"),
        ((0.0, 30.0), (0.0, 1.0), "relative_intensity"),
        ((0.0, 30.0), (1.0, math.nan), "relative_intensity"),
        ((0.0, 30.0), (1.0,), "relative_intensity"),
    ],
)
def test_a_bad_table_names_its_field(
    angles: tuple[float, ...], values: tuple[float, ...], field: str
) -> None:
    with pytest.raises(GeometryError) as caught:
        Beam(angles, values)
    assert caught.value.field == field


def test_a_table_of_cos_m_gives_the_lambertian_channel() -> None:
    layout = paper_layout()
    order = 2.3
    beamed = _with_beams(layout, Beam.lambertian(order, step_deg=1.0))
    points = np.random.default_rng(0).uniform(0.1, 4.9, (40, 2))
    want = _lambertian_gains(layout, points, order)
    np.testing.assert_allclose(channel_gains(beamed, points), want, rtol=1e-4, atol=0.0)


def test_the_interpolant_passes_through_the_table_and_integrates_exactly() -> None:
    arrays = beam_arrays([BATWING])
    cosines = np.cos(np.radians(np.array(BATWING.angles_deg)))[None, :]
    values, _ = evaluate_beams(arrays, cosines)
    np.testing.assert_allclose(values[0], np.array(BATWING.relative_intensity), rtol=1e-12)
    numeric, _ = integrate.quad(
        lambda c: float(evaluate_beams(arrays, np.array([[c]]))[0][0, 0]), 0.0, 1.0, limit=200
    )
    assert BATWING.hemisphere_integral() == pytest.approx(numeric, rel=1e-9)
    assert Beam.lambertian(1.0).hemisphere_integral() == pytest.approx(0.5, rel=1e-12)


def test_the_slope_is_the_interpolant_s_derivative() -> None:
    arrays = beam_arrays([BATWING, None])
    c = np.linspace(0.05, 0.995, 60)[None, :].repeat(2, axis=0)
    step = 1e-6
    values, slopes = evaluate_beams(arrays, c)
    numeric = (evaluate_beams(arrays, c + step)[0] - evaluate_beams(arrays, c - step)[0]) / (
        2 * step
    )
    np.testing.assert_allclose(slopes[0], numeric[0], rtol=1e-5, atol=1e-7)
    assert np.all(values[1] == 1.0) and np.all(slopes[1] == 0.0)  # a Lambertian LED's row


@pytest.mark.parametrize("tilted", [False, True])
def test_gradients_are_those_of_the_gains(tilted: bool) -> None:
    layout = _with_beams(paper_layout(), BATWING, tilt_every_other=tilted)
    points = np.random.default_rng(1).uniform(0.2, 4.8, (30, 2))
    step = 1e-6
    _, gradients = channel_gain_gradients(layout, points)
    for axis in range(2):
        shift = np.eye(2)[axis] * step
        numeric = (
            channel_gains(layout, points + shift) - channel_gains(layout, points - shift)
        ) / (2 * step)
        np.testing.assert_allclose(gradients[:, :, axis], numeric, rtol=1e-5, atol=1e-12)
    xyz = np.column_stack((points, np.linspace(0.3, 1.2, points.shape[0])))
    normals = np.tile([0.1, -0.2, 1.0], (points.shape[0], 1))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    _, gradients_3d = los_gain_gradients(layout, xyz, normals)
    for axis in range(3):
        shift = np.eye(3)[axis] * step
        numeric = (
            los_gains(layout, xyz + shift, normals) - los_gains(layout, xyz - shift, normals)
        ) / (2 * step)
        np.testing.assert_allclose(gradients_3d[:, :, axis], numeric, rtol=1e-5, atol=1e-12)


def test_the_solver_kernel_is_the_channel() -> None:
    """The gridless solver's NumPy kernel against :mod:`app.vlp.channel` (written apart)."""
    layout = _with_beams(paper_layout(), BATWING, tilt_every_other=True)
    kernel = ChannelKernel(layout, 1.0)
    rng = np.random.default_rng(2)
    xs, ys, zs = rng.uniform(0.2, 4.8, 25), rng.uniform(0.2, 4.8, 25), rng.uniform(0.4, 1.2, 25)
    blocks = kernel.gradients_xyz(xs, ys, zs)
    gains, gradients = los_gain_gradients(layout, np.column_stack((xs, ys, zs)))
    pilots = layout.pilot_amplitudes[:, None]
    n = xs.size
    np.testing.assert_allclose(blocks[:, 3 * n : 4 * n], gains * pilots, rtol=1e-10)
    for axis in range(3):
        np.testing.assert_allclose(
            blocks[:, axis * n : (axis + 1) * n],
            gradients[:, :, axis] * pilots,
            rtol=1e-9,
            atol=1e-12 * float(np.max(np.abs(gradients))),
        )
    flat = kernel.gains_xy(xs, ys)
    np.testing.assert_allclose(flat, channel_gains(layout, np.column_stack((xs, ys))) * pilots)


def test_reflections_follow_the_beam_and_keep_the_energy() -> None:
    layout = paper_layout()
    order = 1.7
    angle = float(np.degrees(np.arccos(0.5 ** (1 / order))))
    lambertian = replace(
        layout, leds=tuple(replace(led, half_power_angle_deg=angle) for led in layout.leds)
    )
    assert float(lambertian_order(angle)) == pytest.approx(order)
    tabled = _with_beams(lambertian, Beam.lambertian(order, step_deg=1.0))
    xyz = np.array([[1.0, 2.0, 0.85], [4.0, 0.5, 0.85]])
    from app.vlp.layout import Reflectance

    rho = Reflectance(0.7, 0.2, 0.3)
    np.testing.assert_allclose(
        diffuse_gains(tabled, xyz, reflectance=rho),
        diffuse_gains(lambertian, xyz, reflectance=rho),
        rtol=1e-4,
    )
    batwing = _with_beams(layout, BATWING)  # LEDs flush with the ceiling: none of it escapes
    for index in (0, 3):
        fractions = surface_flux_fractions(batwing, index)
        assert sum(fractions.values()) == pytest.approx(1.0, abs=1e-3)


def test_a_layout_maps_its_beams_both_ways() -> None:
    layout = _with_beams(paper_layout(), BATWING)
    mapping = layout.to_mapping()
    assert mapping["leds"][0]["beam"] == {
        "angles_deg": list(BATWING.angles_deg),
        "relative_intensity": list(BATWING.relative_intensity),
    }
    assert layout_from_mapping(mapping) == layout
    assert "beam" not in paper_layout().to_mapping()["leds"][0]
    mapping["leds"][2]["beam"] = {"angles_deg": [0, 20], "relative_intensity": [1, -1]}
    with pytest.raises(GeometryError) as caught:
        layout_from_mapping(mapping)
    assert caught.value.field == "leds[2].beam.relative_intensity"


def _survey_points(layout: Layout, step: float = 0.4) -> np.ndarray:
    xs = np.arange(step / 2, layout.room.length, step)
    ys = np.arange(step / 2, layout.room.width, step)
    return np.array([(x, y) for x in xs for y in ys])


def _model_error(truth: Layout, model: Layout) -> float:
    """RMS of the amplitude model over the room, relative to the truth's (independent of
    the calibration: the two layouts' channels at fresh points)."""
    points = np.random.default_rng(5).uniform(0.2, 3.8, (300, 2))
    want = channel_gains(truth, points) * truth.pilot_amplitudes[:, None]
    got = channel_gains(model, points) * model.pilot_amplitudes[:, None]
    return float(np.sqrt(np.mean((got - want) ** 2) / np.mean(want**2)))


def test_a_survey_measures_a_batwing_beam_and_leaves_a_lambertian_one() -> None:
    from app.vlp.calibration import calibrate, calibrated_layout
    from app.vlp.survey import simulate_survey

    room = paper_layout()
    batwing_room = _with_beams(room, BATWING)
    points = _survey_points(room)
    lambertian_survey = simulate_survey(room, points, 1e-7, rng=0)
    kept = calibrate(room, lambertian_survey, fit_beams=True)
    assert all(beam is None for beam in kept.beams)  # nothing beyond chance to measure
    survey = simulate_survey(batwing_room, points, 1e-7, rng=0)
    plain = calibrated_layout(room, calibrate(room, survey))
    result = calibrate(room, survey, fit_beams=True)
    measured = calibrated_layout(room, result)
    assert all(beam is not None for beam in result.beams)
    assert all(led.beam is not None for led in measured.leds)
    assert json.loads(json.dumps(result.to_mapping()))["beams"][0]["angles_deg"][:2] == [0, 5]
    assert _model_error(batwing_room, measured) < 0.6 * _model_error(batwing_room, plain)
    # The measured table rises off the axis as the batwing does (1.12 at 30 degrees).
    beam = measured.leds[5].beam
    assert beam is not None
    at_30 = beam.relative_intensity[beam.angles_deg.index(30.0)] / beam.relative_intensity[0]
    assert at_30 > 1.05


def test_a_layout_beam_is_kept_and_its_amplitude_fitted() -> None:
    from app.vlp.calibration import calibrate, calibrated_layout
    from app.vlp.survey import simulate_survey

    nominal = _with_beams(paper_layout(), BATWING)
    brighter = replace(
        nominal, leds=tuple(replace(led, pilot_amplitude=1.3) for led in nominal.leds)
    )
    survey = simulate_survey(brighter, _survey_points(nominal), 1e-8, rng=1)
    result = calibrate(nominal, survey, fit_beams=True, led_tilt_bound_deg=0.0)
    assert result.beams == nominal.beams
    layout = calibrated_layout(nominal, result)
    assert _model_error(brighter, layout) < 1e-3
    # The report keeps the half-power angles the layout states (the beam replaces them).
    np.testing.assert_allclose(result.half_power_angles_deg, nominal.half_power_angles_deg)


def test_the_calibration_jacobian_of_a_beamed_led_is_its_model_s() -> None:
    from app.vlp._calibration_fit import led_rows

    layout = _with_beams(paper_layout(), BATWING)
    points = _survey_points(layout, 0.5)
    rows = led_rows(layout, 5, points, np.ones(points.shape[0]), tilt_bound_deg=10.0)
    shift, tilt, rho = np.array([0.03, -0.02]), np.array([0.2, -0.3]), np.zeros(3)
    columns, _ = rows.jacobian(1.2, 0.0, shift, rho, tilt)
    step = 1e-7
    for column, delta in ((2, (step, 0, 0, 0)), (3, (0, step, 0, 0)), (4, (0, 0, step, 0))):
        move = np.array(delta)
        up = rows.model(1.2, 0.0, shift + move[:2], rho, tilt + move[2:])
        down = rows.model(1.2, 0.0, shift - move[:2], rho, tilt - move[2:])
        np.testing.assert_allclose(
            columns[:, column], (up - down) / (2 * step), rtol=1e-5, atol=1e-9
        )
