"""Tests of app/vlp/calibration.py: recovery of a perturbed room from a simulated survey."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import least_squares

from app.vlp.calibration import (
    CalibrationResult,
    Survey,
    calibrate,
    calibrated_layout,
    half_power_angle_deg,
    masked_layout,
    simulate_survey,
    survey_from_rows,
)
from app.vlp.channel import channel_gains, lambertian_order
from app.vlp.errors import MeasurementError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.typing import FloatArray

DIMMED, DEAD = 3, 9
NOISE_STD = 1e-7  # about 0.7 % of the strongest amplitude in the paper room


def _perturbed(layout: Layout, rng: np.random.Generator) -> tuple[Layout, FloatArray, FloatArray]:
    """The true room: amplitudes +-20 %, angles +-5 deg, one LED at 30 %, one (nearly) dead."""
    amplitudes = layout.pilot_amplitudes * rng.uniform(0.8, 1.2, layout.n_leds)
    angles = layout.half_power_angles_deg + rng.uniform(-5.0, 5.0, layout.n_leds)
    amplitudes[DIMMED] = 0.3 * layout.leds[DIMMED].pilot_amplitude
    amplitudes[DEAD] = 1e-9  # a Layout needs a positive amplitude; this is no signal
    leds = tuple(
        replace(led, pilot_amplitude=float(a), half_power_angle_deg=float(h))
        for led, a, h in zip(layout.leds, amplitudes, angles, strict=True)
    )
    return replace(layout, leds=leds), amplitudes, angles


def _survey_points(layout: Layout, per_side: int = 16) -> FloatArray:
    xs = (np.arange(per_side) + 0.5) * layout.room.length / per_side
    ys = (np.arange(per_side) + 0.5) * layout.room.width / per_side
    return np.array([(x, y) for x in xs for y in ys])


@pytest.fixture(scope="module")
def recovered(paper_room: Layout) -> tuple[Layout, FloatArray, FloatArray, CalibrationResult]:
    true, amplitudes, angles = _perturbed(paper_room, np.random.default_rng(7))
    survey = simulate_survey(
        true, _survey_points(paper_room), NOISE_STD, rng=np.random.default_rng(8)
    )
    return true, amplitudes, angles, calibrate(paper_room, survey)


def test_recovers_true_parameters(
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    _, amplitudes, angles, result = recovered
    live = np.array([i for i in range(len(amplitudes)) if i != DEAD])
    # Only g * x_i is identifiable; the true receiver gain is 1.
    products = result.pilot_amplitudes * result.receiver_gain
    np.testing.assert_allclose(products[live], amplitudes[live], rtol=0.03)
    healthy = live[live != DIMMED]
    np.testing.assert_allclose(result.half_power_angles_deg[healthy], angles[healthy], atol=1.0)
    assert abs(result.half_power_angles_deg[DIMMED] - angles[DIMMED]) < 3.0
    np.testing.assert_allclose(
        result.lambertian_orders[healthy], lambertian_order(angles[healthy]), rtol=0.1
    )
    assert result.converged


def test_receiver_gain_is_the_geometric_mean_of_healthy_leds(
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    _, amplitudes, _, result = recovered
    healthy = [i for i in range(len(amplitudes)) if i not in (DEAD, DIMMED)]
    expected = float(np.exp(np.mean(np.log(amplitudes[healthy]))))
    assert result.receiver_gain == pytest.approx(expected, rel=0.01)
    assert np.exp(np.mean(np.log(result.relative_amplitudes[healthy]))) == pytest.approx(1.0)


def test_flags_dead_and_dimmed_leds(
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    *_, result = recovered
    assert result.dead_leds == (DEAD,)
    assert result.dimmed_leds == (DIMMED,)
    assert result.unsurveyed_leds == ()
    assert result.relative_amplitudes[DIMMED] == pytest.approx(0.3 / result.receiver_gain, rel=0.05)


def test_residuals_drop_to_the_noise_level(
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    *_, result = recovered
    assert np.all(result.residual_rms_after < result.residual_rms_before)
    # Each LED's residual is then pure noise (independent check: the simulated noise std).
    np.testing.assert_allclose(result.residual_rms_after, NOISE_STD, rtol=0.15)
    assert result.noise_std == pytest.approx(NOISE_STD, rel=0.05)
    np.testing.assert_array_equal(result.points_per_led, np.full(16, 256))
    assert np.all(result.points_in_view > 100)


def test_calibrated_layout_reproduces_the_true_amplitudes(
    paper_room: Layout,
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    true, _, _, result = recovered
    model = masked_layout(calibrated_layout(paper_room, result), result.dead_leds)
    reference = masked_layout(true, result.dead_leds)
    points = np.random.default_rng(3).uniform(0.0, 4.0, size=(200, 2))
    got = channel_gains(model, points) * model.pilot_amplitudes[:, None]
    want = channel_gains(reference, points) * reference.pilot_amplitudes[:, None]
    np.testing.assert_allclose(got, want, atol=0.03 * float(want.max()))
    assert model.receiver.filter_gain == pytest.approx(result.receiver_gain)


@pytest.mark.parametrize("bound", [0.0, 0.3], ids=["positions-fixed", "positions-free"])
def test_fit_matches_an_independent_joint_least_squares(paper_room: Layout, bound: float) -> None:
    """Two LEDs fitted jointly by a plain solver (4 parameters, or 8 with the LEDs' x, y)
    agree with the per-LED fit."""
    true, _, _ = _perturbed(paper_room, np.random.default_rng(11))
    true = replace(true, leds=(replace(true.leds[0], x=0.62, y=0.41), *true.leds[1:]))
    survey = simulate_survey(
        true, _survey_points(paper_room, 10), 2e-7, rng=np.random.default_rng(12)
    )
    keep = survey.led_indices < 2
    sub = replace(paper_room, leds=paper_room.leds[:2])
    small = Survey(survey.points[keep], survey.led_indices[keep], survey.amplitudes[keep])
    result = calibrate(
        sub,
        small,
        dimmed_below=0.0,
        dead_below=0.0,
        led_position_bound_m=bound,
        led_tilt_bound_deg=0.0,
    )
    free = bound > 0

    def residuals(params: FloatArray) -> FloatArray:
        leds = tuple(
            replace(
                led,
                pilot_amplitude=float(params[k]),
                half_power_angle_deg=float(half_power_angle_deg(params[2 + k])),
                x=float(params[4 + k]) if free else led.x,
                y=float(params[6 + k]) if free else led.y,
            )
            for k, led in enumerate(sub.leds)
        )
        trial = replace(sub, leds=leds)
        gains = channel_gains(trial, small.points) * trial.pilot_amplitudes[:, None]
        return np.asarray(
            (gains[small.led_indices, np.arange(small.n_rows)] - small.amplitudes) * 1e5
        )

    nominal_xy = sub.led_positions[:, :2]
    start = [1.0, 1.0, 1.0, 1.0] + (list(nominal_xy[:, 0]) + list(nominal_xy[:, 1]) if free else [])
    lower = [1e-6, 1e-6, 0.2, 0.2] + (list(nominal_xy.T.ravel() - bound) if free else [])
    upper = [10, 10, 50, 50] + (list(nominal_xy.T.ravel() + bound) if free else [])
    joint = least_squares(residuals, np.array(start), bounds=(lower, upper), xtol=1e-12)
    products = result.pilot_amplitudes * result.receiver_gain
    np.testing.assert_allclose(products, joint.x[:2], rtol=1e-4)
    np.testing.assert_allclose(result.lambertian_orders, joint.x[2:4], rtol=1e-3)
    if free:
        np.testing.assert_allclose(result.led_positions, joint.x[4:].reshape(2, 2).T, atol=1e-4)
        # ... and the displaced LED is found near where it is (0.12 m, 0.09 m off; the noise
        # leaves a centimetre or two in this corner).
        np.testing.assert_allclose(result.led_positions[0], (0.62, 0.41), atol=0.03)
        np.testing.assert_allclose(result.led_shifts_m[0], (0.12, -0.09), atol=0.03)
    else:
        np.testing.assert_array_equal(result.led_shifts_m, 0.0)


def test_uniformly_weaker_receiver_is_not_mistaken_for_dimmed_leds(paper_room: Layout) -> None:
    weak = replace(paper_room, receiver=replace(paper_room.receiver, filter_gain=0.4))
    survey = simulate_survey(weak, _survey_points(paper_room, 8), 0.0)
    result = calibrate(paper_room, survey)
    assert result.receiver_gain == pytest.approx(0.4, rel=1e-6)
    np.testing.assert_allclose(result.pilot_amplitudes, 1.0, rtol=1e-6)
    np.testing.assert_allclose(result.half_power_angles_deg, 60.0, atol=1e-4)
    assert result.dead_leds == result.dimmed_leds == ()
    np.testing.assert_allclose(result.residual_rms_after, 0.0, atol=1e-12)


def test_led_without_points_in_view_keeps_nominal_values() -> None:
    layout = Layout(
        Room(12.0, 4.0, 3.0),
        Grid(0.5, 0.85),
        (Led(1.0, 2.0, 3.0, 55.0), Led(11.0, 2.0, 3.0, 65.0)),
        Receiver(fov_deg=40.0),
    )
    points = np.array([(x, y) for x in (0.5, 1.0, 1.5, 2.0) for y in (1.0, 2.0, 3.0)])
    result = calibrate(layout, simulate_survey(layout, points))
    assert result.unsurveyed_leds == (1,)
    assert result.points_in_view.tolist() == [12, 0]
    assert result.half_power_angles_deg[1] == pytest.approx(65.0)
    assert result.half_power_angles_deg[0] == pytest.approx(55.0, abs=1e-6)
    assert result.receiver_gain == pytest.approx(1.0)


def test_few_points_in_view_fit_the_amplitude_only(paper_room: Layout) -> None:
    layout = replace(paper_room, leds=paper_room.leds[:1])
    true = replace(layout, leds=(replace(layout.leds[0], pilot_amplitude=0.7),))
    result = calibrate(layout, simulate_survey(true, np.array([[0.6, 0.4], [1.0, 1.0]])))
    assert result.lambertian_orders[0] == pytest.approx(1.0)  # nominal, not fitted
    assert result.pilot_amplitudes[0] * result.receiver_gain == pytest.approx(0.7)


def test_masked_layout_drops_fingerprint_rows(paper_room: Layout) -> None:
    dropped = (2, 5, 15)
    masked = masked_layout(paper_room, dropped)
    assert masked.n_leds == paper_room.n_leds - len(dropped)
    full = build_fingerprint(paper_room).dense_gains()
    kept = [i for i in range(paper_room.n_leds) if i not in dropped]
    np.testing.assert_array_equal(build_fingerprint(masked).dense_gains(), full[kept])


def test_half_power_angle_inverts_lambertian_order() -> None:
    angles = np.array([10.0, 30.0, 60.0, 85.0])
    np.testing.assert_allclose(half_power_angle_deg(lambertian_order(angles)), angles)


def test_survey_from_rows_and_simulated_layout_order(paper_room: Layout) -> None:
    survey = simulate_survey(paper_room, np.array([[1.0, 1.0], [2.0, 3.0]]))
    assert survey.n_rows == 32
    rows = np.column_stack((survey.points, survey.led_indices, survey.amplitudes)).astype(float)
    again = survey_from_rows(rows)
    np.testing.assert_array_equal(again.led_indices, survey.led_indices)
    expected = channel_gains(paper_room, np.array([[2.0, 3.0]]))[:, 0]
    np.testing.assert_allclose(survey.amplitudes[16:], expected)


@pytest.mark.parametrize(
    ("points", "indices", "amplitudes", "field"),
    [
        (np.zeros((3, 3)), np.zeros(3), np.zeros(3), "points"),
        (np.zeros((3, 2)), np.zeros(2), np.zeros(3), "led_indices"),
        (np.zeros((3, 2)), np.zeros(3), np.zeros(4), "amplitudes"),
        (np.full((3, 2), np.nan), np.zeros(3), np.zeros(3), "points"),
        (np.zeros((3, 2)), np.zeros(3), np.array([0.0, np.inf, 0.0]), "amplitudes"),
        (np.zeros((3, 2)), np.array([0.0, 0.5, 1.0]), np.zeros(3), "led_indices"),
        (np.zeros((0, 2)), np.zeros(0), np.zeros(0), "points"),
    ],
    ids=[
        "points-shape",
        "index-shape",
        "amp-shape",
        "points-nan",
        "amp-inf",
        "index-frac",
        "empty",
    ],
)
def test_survey_rejects_bad_input(
    points: FloatArray, indices: FloatArray, amplitudes: FloatArray, field: str
) -> None:
    with pytest.raises(MeasurementError) as info:
        Survey(points, indices, amplitudes)  # type: ignore[arg-type]
    assert info.value.field == field


@pytest.mark.parametrize(
    ("point", "index", "field"),
    [
        ((1.0, 1.0), 16, "led_indices"),
        ((1.0, 1.0), -1, "led_indices"),
        ((4.5, 1.0), 0, "points"),
        ((1.0, -0.1), 0, "points"),
    ],
    ids=["index-high", "index-negative", "x-outside", "y-outside"],
)
def test_calibrate_rejects_rows_that_do_not_fit_the_room(
    paper_room: Layout, point: tuple[float, float], index: int, field: str
) -> None:
    survey = Survey(np.array([point, (2.0, 2.0)]), np.array([index, 0]), np.ones(2))
    with pytest.raises(MeasurementError) as info:
        calibrate(paper_room, survey)
    assert info.value.field == field


def test_layout_functions_reject_bad_input(
    paper_room: Layout,
    recovered: tuple[Layout, FloatArray, FloatArray, CalibrationResult],
) -> None:
    with pytest.raises(MeasurementError) as info:
        masked_layout(paper_room, [16])
    assert info.value.field == "dead_leds"
    with pytest.raises(MeasurementError) as info:
        masked_layout(paper_room, list(range(16)))
    assert info.value.field == "dead_leds"
    with pytest.raises(MeasurementError) as info:
        calibrated_layout(replace(paper_room, leds=paper_room.leds[:4]), recovered[3])
    assert info.value.field == "result"
    with pytest.raises(MeasurementError) as info:
        survey_from_rows(np.zeros((3, 3)))
    assert info.value.field == "rows"


def test_result_mapping_is_json_ready(paper_room: Layout) -> None:
    layout = replace(paper_room, leds=paper_room.leds[:2])
    points = np.array([[0.4, 0.4], [0.6, 0.7], [1.0, 0.2], [0.2, 1.1]])
    survey = simulate_survey(layout, points)
    only_first = Survey(survey.points[::2], survey.led_indices[::2], survey.amplitudes[::2])
    mapping = calibrate(layout, only_first).to_mapping()
    assert json.loads(json.dumps(mapping, allow_nan=False)) == mapping
    assert mapping["points_per_led"] == [4, 0]
    assert mapping["residual_rms_after"][1] is None
    assert mapping["unsurveyed_leds"] == [1]
    assert mapping["pilot_amplitudes"][0] == pytest.approx(1.0)


def test_survey_of_a_dark_room_flags_every_led_dead(paper_room: Layout) -> None:
    survey = simulate_survey(paper_room, _survey_points(paper_room, 6))
    noise = np.random.default_rng(2).normal(0.0, 1e-7, survey.n_rows)
    dark = Survey(survey.points, survey.led_indices, noise)
    result = calibrate(paper_room, dark)
    assert result.dead_leds == tuple(range(16))
    assert result.receiver_gain == 1.0
    np.testing.assert_allclose(result.pilot_amplitudes, paper_room.pilot_amplitudes)
    np.testing.assert_allclose(result.residual_rms_after, 1e-7, rtol=0.3)


@pytest.mark.parametrize(
    ("dimmed", "dead"),
    [(0.5, 0.6), (1.5, 0.1), (0.5, -0.1)],
    ids=["dead-above-dimmed", "dimmed-above-one", "dead-negative"],
)
def test_calibrate_rejects_bad_thresholds(paper_room: Layout, dimmed: float, dead: float) -> None:
    survey = simulate_survey(paper_room, np.array([[1.0, 1.0]]))
    with pytest.raises(MeasurementError) as info:
        calibrate(paper_room, survey, dimmed_below=dimmed, dead_below=dead)
    assert info.value.field == "dimmed_below"
