"""``bench/measured_floor.py`` on small synthetic surveys whose noise and beams are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench import measured_floor
from bench._massey import MasseySurvey

LEDS = np.array([[0.6, 0.6, 2.35], [0.6, 2.4, 2.35], [2.4, 0.6, 2.35], [2.4, 2.4, 2.35]])
DROP = 1.45
ORDER = 1.0
LOG_SCALE = math.log(4.0e4)


def _log_readings(points: np.ndarray) -> np.ndarray:
    """Lambertian log readings (order 1, level receiver DROP below the LEDs), written out."""
    r2 = ((points[:, None, :] - LEDS[None, :, :2]) ** 2).sum(axis=-1)
    return np.asarray(
        LOG_SCALE + (ORDER + 1) * math.log(DROP) - (ORDER + 3) / 2 * np.log(DROP**2 + r2)
    )


def test_repeat_noise_recovers_a_known_multiplicative_noise() -> None:
    rng = np.random.default_rng(3)
    ticks = 0.3 + 0.12 * np.arange(20)  # places far apart, so only the twins pair up
    places = np.array([(x, y) for x in ticks for y in ticks])
    # each place measured twice, 5 mm apart (the same place for the log readings)
    points = np.r_[places, places + 0.005]
    clean = np.exp(_log_readings(points))
    readings = clean * np.exp(0.08 * rng.standard_normal(clean.shape))
    log_sd, pairs, by_level = measured_floor.repeat_noise(points, readings)
    assert pairs == 400
    assert log_sd == pytest.approx(0.08, rel=0.08)  # 1,600 log ratios: sd known to ~2 %
    assert by_level and all(count >= 10 for *_, count in by_level)


def test_radial_profiles_reproduce_a_smooth_beam_and_its_slope() -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(0.1, 2.9, size=(600, 2))
    distances = measured_floor.horizontal_distances(points, LEDS)
    profiles = measured_floor.RadialProfiles.fit(
        distances, np.exp(_log_readings(points)), measured_floor.DENSE_KNOTS_M
    )
    probe = rng.uniform(0.3, 2.7, size=(50, 2))
    probe_distances = measured_floor.horizontal_distances(probe, LEDS)
    np.testing.assert_allclose(profiles.log_model(probe_distances), _log_readings(probe), atol=2e-3)
    # d/dr of the Lambertian log model: -(m + 3) r / (dz^2 + r^2)
    slope = -(ORDER + 3) * probe_distances / (DROP**2 + probe_distances**2)
    np.testing.assert_allclose(profiles.slopes(probe_distances), slope, atol=2e-2)


def test_lambertian_beams_recover_their_order_and_scale() -> None:
    rng = np.random.default_rng(5)
    points = rng.uniform(0.1, 2.9, size=(100, 2))
    distances = measured_floor.horizontal_distances(points, LEDS)
    beams = measured_floor.LambertianBeams.fit(distances, np.exp(_log_readings(points)), DROP)
    np.testing.assert_allclose(beams.orders, ORDER, atol=1e-6)
    np.testing.assert_allclose(beams.log_scales, LOG_SCALE, atol=1e-6)


def test_the_bound_of_one_fix_is_its_fisher_information_inverse() -> None:
    survey_points = np.random.default_rng(6).uniform(0.1, 2.9, size=(600, 2))
    profiles = measured_floor.RadialProfiles.fit(
        measured_floor.horizontal_distances(survey_points, LEDS),
        np.exp(_log_readings(survey_points)),
        measured_floor.DENSE_KNOTS_M,
    )
    point = np.array([[1.1, 1.7]])
    sd = 0.1
    errors = measured_floor.bound_errors(
        profiles, LEDS, point, np.ones((1, 4), dtype=bool), sd, free_gain=False, draws=20_000
    )
    # Independently: Fisher information of four log readings, slopes of the Lambertian model.
    offsets = point[0] - LEDS[:, :2]
    r = np.hypot(*offsets.T)
    rows = (-(ORDER + 3) * r / (DROP**2 + r**2))[:, None] * offsets / r[:, None]
    covariance = np.linalg.inv(rows.T @ rows / sd**2)
    # E|e|^2 = trace of the covariance
    assert np.mean(errors**2) == pytest.approx(np.trace(covariance), rel=0.05)


def test_a_noiseless_survey_is_fixed_where_it_was_taken() -> None:
    rng = np.random.default_rng(8)
    points = rng.uniform(0.3, 2.7, size=(300, 2))
    readings = np.exp(_log_readings(points))
    distances = measured_floor.horizontal_distances(points, LEDS)
    beams = measured_floor.LambertianBeams.fit(distances, readings, DROP)
    test = points[:20]
    bounds = (np.zeros(2), np.full(2, 3.0))
    for free_gain in (False, True):
        found = measured_floor.grid_fixes(beams, LEDS, readings[:20], bounds, free_gain=free_gain)
        assert np.max(np.hypot(*(found - test).T)) <= measured_floor.FINE_STEP_M


def test_leave_one_out_knn_never_uses_the_point_itself() -> None:
    # Two clusters of identical readings: the point's own reading would put it exactly on
    # itself; without it, the estimate is the mean of its cluster's other points.
    points = np.array(
        [
            [0.0, 0.0],
            [1.0, 0.0],
            [0.0, 1.0],
            [1.0, 1.0],
            [5.0, 5.0],
            [6.0, 5.0],
            [5.0, 6.0],
            [6.0, 6.0],
            [5.5, 5.5],
        ]
    )
    readings = np.array([[100.0, 20.0]] * 4 + [[20.0, 100.0]] * 5)
    survey = MasseySurvey(leds=LEDS[:2], points=points, readings=readings)
    found = measured_floor.leave_one_out_knn(survey, np.array([8]), k=4)
    np.testing.assert_allclose(found[0], [5.5, 5.5])
    found = measured_floor.leave_one_out_knn(survey, np.array([0]), k=3)
    np.testing.assert_allclose(found[0], [2 / 3, 2 / 3])


def test_the_angular_profile_of_a_lambertian_beam_is_its_cosine() -> None:
    rng = np.random.default_rng(9)
    points = rng.uniform(-1.5, 4.5, size=(20000, 2))  # >= 8 per bin and LED
    survey = MasseySurvey(leds=LEDS, points=points, readings=np.exp(_log_readings(points)))
    edges, relative = measured_floor.angular_profile(survey, DROP)
    # order 1: reading * d^2 / cos(incidence) = C cos(angle off the axis), so each bin's
    # median over the median within 20 degrees is a ratio of cosines of the same points
    angle = np.degrees(np.arctan(measured_floor.horizontal_distances(points, LEDS) / DROP))
    cosine = np.cos(np.radians(angle))
    expected = [
        np.median(
            [
                np.median(cosine[(angle[:, i] >= e) & (angle[:, i] < e + 5), i])
                / np.median(cosine[angle[:, i] < 20, i])
                for i in range(len(LEDS))
            ]
        )
        for e in edges[:12]
    ]
    np.testing.assert_allclose(relative[:12], expected, rtol=1e-9)
