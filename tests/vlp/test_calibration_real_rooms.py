"""Calibration in real rooms: LED positions, reflectances, a drifted survey.

The surveys are simulated independently of the fit's model: line of sight by
:func:`app.vlp.channel.los_gains` from the TRUE LEDs, the first diffuse bounce off the TRUE
surfaces with finer quadrature cells (:data:`TRUE_ELEMENT_SIZE_M`) than the fit's, at the
noise of 30 dB in the service's SNR convention.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.schemas.calibrations import DEFAULT_LED_POSITION_BOUND_M as SCHEMA_BOUND
from app.vlp.calibration import (
    DEFAULT_LED_POSITION_BOUND_M,
    Survey,
    calibrate,
    calibrated_layout,
    simulate_survey,
)
from app.vlp.channel import los_gains
from app.vlp.errors import MeasurementError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.presets import paper_layout
from app.vlp.reflections import diffuse_gains
from app.vlp.simulation import (
    TRUE_ELEMENT_SIZE_M,
    Impairments,
    noise_std_for_snr,
    random_positions,
    simulate_terminals,
)
from app.vlp.solvers import make_solver
from app.vlp.typing import FloatArray

WALLS = Reflectance(walls=0.6, floor=0.0, ceiling=0.0)
MOVED = {3: (0.2, -0.1), 9: (-0.15, 0.25)}


@pytest.fixture(scope="module")
def room() -> Layout:
    return paper_layout()


@pytest.fixture(scope="module")
def sigma(room: Layout) -> float:
    return noise_std_for_snr(build_fingerprint(room), 30.0)


def _points(room: Layout, step: float = 0.5) -> FloatArray:
    xs = np.arange(step / 2, room.room.length, step)
    ys = np.arange(step / 2, room.room.width, step)
    return np.array([(x, y) for x in xs for y in ys])


def _true_room(room: Layout, moved: dict[int, tuple[float, float]]) -> Layout:
    leds = tuple(
        replace(led, x=led.x + moved.get(i, (0, 0))[0], y=led.y + moved.get(i, (0, 0))[1])
        for i, led in enumerate(room.leds)
    )
    return replace(room, room=replace(room.room, reflectance=WALLS), leds=leds)


def _clean_survey(true: Layout, points: FloatArray) -> FloatArray:
    """(P, M) amplitudes: independent LoS plus a finer first bounce, no noise."""
    xyz = np.column_stack((points, np.full(points.shape[0], true.grid.receiver_height)))
    gains = los_gains(true, xyz) + diffuse_gains(true, xyz, element_size_m=TRUE_ELEMENT_SIZE_M)
    return np.asarray((gains * true.pilot_amplitudes[:, None]).T)


def _survey(points: FloatArray, clean: FloatArray, sigma: float, seed: int) -> Survey:
    n_leds = clean.shape[1]
    noisy = clean + sigma * np.random.default_rng(seed).standard_normal(clean.shape)
    return Survey(
        np.repeat(points, n_leds, axis=0),
        np.tile(np.arange(n_leds), points.shape[0]),
        noisy.ravel(),
    )


def test_fitted_led_positions_recover_a_known_displacement(room: Layout, sigma: float) -> None:
    true = _true_room(room, MOVED)
    points = _points(room)
    survey = _survey(points, _clean_survey(true, points), sigma, seed=1)
    given = replace(room, room=replace(room.room, reflectance=WALLS))
    result = calibrate(given, survey)
    expected = np.zeros((room.n_leds, 2))
    for i, shift in MOVED.items():
        expected[i] = shift
    # 64 points at 30 dB: a few centimetres of noise per LED (3 cm covers them here).
    np.testing.assert_allclose(result.led_shifts_m, expected, atol=0.03)
    np.testing.assert_allclose(result.led_positions, true.led_positions[:, :2], atol=0.03)
    # Without the position fit (nor a tilt, which would mimic part of a shift near the LED's
    # foot) the moved LEDs are mis-modelled: residuals far above the noise.
    fixed = calibrate(given, survey, led_position_bound_m=0.0, led_tilt_bound_deg=0.0)
    moved = list(MOVED)
    assert np.all(fixed.residual_rms_after[moved] > 1.5 * result.residual_rms_after[moved])
    assert np.all(result.residual_rms_after[moved] < 1.3 * sigma)
    # The calibrated layout carries the fitted positions.
    layout = calibrated_layout(given, result)
    np.testing.assert_allclose(layout.led_positions[:, :2], result.led_positions)


def test_position_bound_holds(room: Layout, sigma: float) -> None:
    true = _true_room(room, {5: (0.4, 0.0)})
    points = _points(room)
    survey = _survey(points, _clean_survey(true, points), sigma, seed=2)
    result = calibrate(replace(room, room=replace(room.room, reflectance=WALLS)), survey)
    assert np.max(np.abs(result.led_shifts_m)) <= DEFAULT_LED_POSITION_BOUND_M + 1e-12
    assert result.led_shifts_m[5, 0] == pytest.approx(DEFAULT_LED_POSITION_BOUND_M)
    assert SCHEMA_BOUND == DEFAULT_LED_POSITION_BOUND_M
    with pytest.raises(MeasurementError) as info:
        calibrate(room, survey, led_position_bound_m=1.5)
    assert info.value.field == "led_position_bound_m"


@pytest.mark.slow
def test_reflectance_recovers_a_known_value_within_its_uncertainty(
    room: Layout, sigma: float
) -> None:
    """The layout says line of sight only; the walls reflect 0.6. Over 12 noise draws the
    fitted value's errors, in units of its reported sd, have an RMS near 1 (the sd is
    honest) and none is beyond 3."""
    true = _true_room(room, {})
    points = _points(room)
    clean = _clean_survey(true, points)
    z_scores, sds = [], []
    for seed in range(12):
        result = calibrate(room, _survey(points, clean, sigma, seed), fit_reflectance=True)
        assert result.reflectance is not None
        sd = float(result.reflectance_sd[0])
        z_scores.append((result.reflectance.walls - WALLS.walls) / sd)
        sds.append(sd)
        # Receivers facing up with a 70 degree FOV see neither floor nor ceiling lit: those
        # are not fitted (kept at 0, no sd).
        assert np.isnan(result.reflectance_sd[1:]).all()
        assert result.reflectance.floor == result.reflectance.ceiling == 0.0
    z = np.array(z_scores)
    assert np.max(np.abs(z)) < 3.0
    assert 0.5 < float(np.sqrt(np.mean(z**2))) < 1.6
    assert max(sds) < 0.08
    layout = calibrated_layout(room, result)
    assert layout.room.reflectance == result.reflectance


def test_reflectance_fit_is_exact_without_noise(room: Layout) -> None:
    """Noiseless survey computed with the fit's own quadrature: the walls come out exact
    (to the quadrature's 1e-4, which moves with the LEDs' fitted positions)."""
    true = replace(room, room=replace(room.room, reflectance=Reflectance(0.45, 0.0, 0.0)))
    survey = simulate_survey(true, _points(room, 1.0))
    result = calibrate(room, survey, fit_reflectance=True)
    assert result.reflectance is not None
    assert result.reflectance.walls == pytest.approx(0.45, abs=1e-3)
    np.testing.assert_allclose(result.led_shifts_m, 0.0, atol=1e-3)
    np.testing.assert_allclose(result.relative_amplitudes, 1.0, rtol=1e-3)


# A terminal drifted by 17 %: the survey receiver of another day is this much more (or less)
# sensitive than the terminals.
DRIFT = 1.17
# A drifted survey localizes within this factor (plus 5 mm) of the undrifted one.
DRIFT_FACTOR = 1.25


def _drift_room(room: Layout) -> Layout:
    rng = np.random.default_rng(5)
    return replace(
        room,
        leds=tuple(
            replace(
                led,
                pilot_amplitude=float(np.exp(0.05 * rng.standard_normal())),
                half_power_angle_deg=60.0 + 3.0 * float(rng.standard_normal()),
            )
            for led in room.leds
        ),
    )


def _localize_after_survey(
    room: Layout, true: Layout, drift: float, sigma: float, *, apply_receiver_gain: bool
) -> tuple[float, list[int]]:
    """Mean matched error (K = 4 given) and the counts (K not given) over 8 trials."""
    survey = simulate_survey(true, _points(room), sigma, rng=1, receiver_gain=drift)
    result = calibrate(room, survey)
    assert result.receiver_gain == pytest.approx(drift, rel=0.05)
    layout = calibrated_layout(room, result, apply_receiver_gain=apply_receiver_gain)
    solver = make_solver("gridless", build_fingerprint(layout), "correlation")
    errors, counts = [], []
    for trial in range(8):
        positions = random_positions(room, 4, rng=100 + trial)
        measured = simulate_terminals(true, positions, Impairments.ideal(), snr_db=30.0, rng=trial)
        measurement = measurement_from_amplitudes(measured.amplitudes, "correlation", room.n_leds)
        errors.append(mean_position_error(solver.solve(measurement, 4).positions, positions))
        counts.append(solver.solve(measurement).positions.shape[0])
    return float(np.mean(errors)), counts


@pytest.mark.parametrize("drift", [DRIFT, 1 / DRIFT], ids=["up", "down"])
def test_survey_from_a_drifted_receiver_still_localizes(
    room: Layout, sigma: float, drift: float
) -> None:
    """Gain folded in (the default): the fingerprint is off the terminals by the drift; with
    K given the solver's scale and gain nuisances absorb it."""
    true = _drift_room(room)
    undrifted, _ = _localize_after_survey(room, true, 1.0, sigma, apply_receiver_gain=True)
    drifted, _ = _localize_after_survey(room, true, drift, sigma, apply_receiver_gain=True)
    assert drifted <= DRIFT_FACTOR * undrifted + 0.005


@pytest.mark.parametrize("drift", [DRIFT, 1 / DRIFT], ids=["up", "down"])
def test_survey_receiver_gain_left_out_localizes_and_counts(
    room: Layout, sigma: float, drift: float
) -> None:
    """``apply_receiver_gain=False``: the drift stays in the reported receiver gain, the
    fingerprint is the undrifted one to the noise, so targets are located AND counted as
    after an undrifted survey."""
    true = _drift_room(room)
    undrifted, reference = _localize_after_survey(room, true, 1.0, sigma, apply_receiver_gain=False)
    drifted, counts = _localize_after_survey(room, true, drift, sigma, apply_receiver_gain=False)
    assert drifted <= DRIFT_FACTOR * undrifted + 0.005
    right, reference_right = counts.count(4), reference.count(4)
    assert right >= reference_right - 1 and right >= 6, (counts, reference)
