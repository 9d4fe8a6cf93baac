"""Radii of terminals in a calibrated room: the room's amplitude scatter, measured by its
survey calibration, weights each terminal and is its covariance's variance."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import integrate, stats

from app.vlp import uncertainty
from app.vlp.calibration import calibrate, calibrated_layout
from app.vlp.errors import GeometryError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import AmplitudeError, Layout
from app.vlp.layout_mapping import layout_from_mapping
from app.vlp.radii import confidence_radius
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers.gridless import GridlessSolver, terminal_solve, terminal_weights
from app.vlp.survey import survey_from_rows
from app.vlp.uncertainty import Misfit
from tests.terminal_information import position_covariance


def _mass_inside(covariance: np.ndarray, radius: float) -> float:
    """P(|e| <= radius) for e ~ N(0, covariance), by 2-D quadrature in polar coordinates
    (independent of the solver's radial root finding)."""
    precision = np.linalg.inv(covariance)
    norm = 1.0 / (2.0 * math.pi * math.sqrt(np.linalg.det(covariance)))

    def density(r: float, angle: float) -> float:
        u = np.array([math.cos(angle), math.sin(angle)])
        return float(norm * math.exp(-0.5 * r * r * (u @ precision @ u)) * r)

    mass, _ = integrate.dblquad(density, 0.0, 2.0 * math.pi, 0.0, radius, epsabs=1e-10)
    return float(mass)


def _recorded_verdicts(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """The verdicts of ``scatter_explains`` in the terminal solve, as they are given."""
    verdicts: list[bool] = []
    explains = terminal_weights.scatter_explains

    def recorded(*args, **kwargs):  # type: ignore[no-untyped-def]
        verdicts.append(explains(*args, **kwargs))
        return verdicts[-1]

    monkeypatch.setattr(terminal_solve, "scatter_explains", recorded)
    return verdicts


def test_a_scatter_on_many_degrees_of_freedom_gives_the_chi_square_radius(
    paper_room: Layout,
) -> None:
    # A level receiver in the middle of the paper room, its amplitudes with a noise of the
    # room's measured sd: the covariance is the inverse of the weighted fit's information
    # (the gain's 10 % prior included), not widened, and its 95 % circle holds 95 % of
    # that Gaussian (a quadrature of the density, not the radius code).
    noise_sd = 3e-7
    layout = replace(
        paper_room,
        grid=replace(paper_room.grid, receivers_level=True),
        amplitude_error=AmplitudeError(noise_sd=noise_sd, relative_sd=0.0, dof=1e9),
    )
    solver = GridlessSolver(build_fingerprint(layout), "correlation")
    truth = np.array([[1.9, 2.2]])
    clean = true_amplitudes(layout, truth)
    amplitudes = clean + noise_sd * np.random.default_rng(3).standard_normal(clean.shape)
    # Its height sent and its photodiode level: no error of its own is left to estimate.
    height = np.array([layout.grid.receiver_height])
    solution = solver.solve_terminals(amplitudes, heights=height)
    assert solution.covariances is not None
    gain = float(solution.gains[0]) if solution.gains is not None else 1.0
    expected = position_covariance(layout, solution.positions[0], gain, noise_sd)
    np.testing.assert_allclose(solution.covariances[0], expected, rtol=2e-3)
    radius = confidence_radius(solution.covariances[0])
    assert _mass_inside(expected, radius) == pytest.approx(0.95, abs=2e-3)
    # Round enough here that the radius is close to the chi-square(2) one of its trace.
    round_sd = math.sqrt(np.trace(expected) / 2.0)
    assert radius == pytest.approx(math.sqrt(stats.chi2.ppf(0.95, 2)) * round_sd, rel=0.1)


def test_a_scatter_on_few_degrees_of_freedom_widens_the_radius(paper_room: Layout) -> None:
    # The same terminal, the scatter estimated from 4 degrees of freedom: F(2, 4) instead of
    # chi-square(2), 2 F^-1(0.95; 2, 4) / chi2^-1(0.95; 2) = 2.31 times the covariance.
    amplitudes = true_amplitudes(paper_room, np.array([[1.9, 2.2]]))
    amplitudes = amplitudes + 3e-7 * np.random.default_rng(3).standard_normal(amplitudes.shape)
    radii = []
    for dof in (1e9, 4.0):
        layout = replace(
            paper_room,
            grid=replace(paper_room.grid, receivers_level=True),
            amplitude_error=AmplitudeError(noise_sd=3e-7, relative_sd=0.0, dof=dof),
        )
        solution = GridlessSolver(build_fingerprint(layout), "correlation").solve_terminals(
            amplitudes, heights=np.array([layout.grid.receiver_height])
        )
        assert solution.covariances is not None
        radii.append(confidence_radius(solution.covariances[0]))
    widening = 2.0 * stats.f.ppf(0.95, 2, 4) / stats.chi2.ppf(0.95, 2)
    assert radii[1] == pytest.approx(radii[0] * math.sqrt(widening), rel=1e-3)


@pytest.mark.parametrize("measured", [False, True], ids=["uncalibrated", "scatter-exceeded"])
def test_without_a_calibration_the_radius_rests_on_the_requests_own_residuals(
    paper_room: Layout, monkeypatch: pytest.MonkeyPatch, measured: bool
) -> None:
    # No measured scatter, or one that the request's residuals exceed in a layout that does not
    # say the receivers are level (terminals unlike the survey receiver): the covariances use
    # the variances fitted to the request's own residuals (pooled over its terminals), on
    # their few degrees of freedom.
    assert paper_room.amplitude_error is None and not paper_room.grid.receivers_level
    if measured:
        # A tenth of the relative error the amplitudes below carry.
        scatter = AmplitudeError(noise_sd=1e-7, relative_sd=0.003, dof=1e9)
        paper_room = replace(paper_room, amplitude_error=scatter)
    pooled: list[Misfit] = []
    used: list[Misfit] = []
    fit_pooled, covariances_of = uncertainty.fit_misfit, uncertainty.predictive_covariances

    def fitting(designs, residuals, *args, **kwargs):  # type: ignore[no-untyped-def]
        pooled.append(fit_pooled(designs, residuals, *args, **kwargs))
        return pooled[-1]

    def covariances(design, misfit, blocks, level=0.95):  # type: ignore[no-untyped-def]
        used.append(misfit)
        return covariances_of(design, misfit, blocks, level)

    monkeypatch.setattr(terminal_solve, "fit_misfit", fitting)
    monkeypatch.setattr(terminal_solve, "predictive_covariances", covariances)
    clean = true_amplitudes(paper_room, np.array([[1.3, 2.6], [2.9, 0.8]]))
    rng = np.random.default_rng(8)
    amplitudes = clean * (1.0 + 0.03 * rng.standard_normal(clean.shape))
    amplitudes = amplitudes + 0.01 * float(np.mean(clean)) * rng.standard_normal(clean.shape)
    solver = GridlessSolver(build_fingerprint(paper_room), "correlation")
    solver.solve_terminals(amplitudes)
    assert len(used) == 2 and all(misfit is pooled[-1] for misfit in used)
    assert 0 < pooled[-1].dofs[0] < 2 * paper_room.n_leds


def test_terminals_the_scatter_explains_are_weighted_by_it_without_a_level_layout(
    paper_room: Layout,
) -> None:
    # Level terminals whose amplitudes scatter as the survey measured: a layout that says
    # nothing about the receivers' tilt gives them the answer of one that says they are level
    # (the same weights and radii: their fits keep no tilt), where the request's own few
    # residuals would have estimated the variances.
    scatter = AmplitudeError(noise_sd=2e-7, relative_sd=0.03, dof=300.0)
    silent = replace(paper_room, amplitude_error=scatter)
    level = replace(silent, grid=replace(silent.grid, receivers_level=True))
    clean = true_amplitudes(silent, np.array([[1.3, 2.6], [2.9, 0.8], [0.7, 0.9]]))
    rng = np.random.default_rng(5)
    amplitudes = clean * (1.0 + scatter.relative_sd * rng.standard_normal(clean.shape))
    amplitudes = amplitudes + scatter.noise_sd * rng.standard_normal(clean.shape)
    answers = [
        GridlessSolver(build_fingerprint(layout), "correlation").solve_terminals(amplitudes)
        for layout in (silent, level, paper_room)
    ]
    assert answers[0].covariances is not None and answers[1].covariances is not None
    # The same optimum, each fit reached from its own first pass (to LM's tolerance).
    np.testing.assert_allclose(answers[0].positions, answers[1].positions, rtol=1e-6)
    np.testing.assert_allclose(answers[0].covariances, answers[1].covariances, rtol=1e-4)
    # Without the calibration's scatter the same request is answered otherwise.
    assert not np.allclose(answers[2].positions, answers[0].positions, rtol=0, atol=1e-6)


def test_terminals_the_scatter_does_not_explain_are_placed_by_it_with_their_own_radii(
    paper_room: Layout, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Amplitudes scattered five times as widely as the survey measured: the scatter does not
    # explain them, yet their positions are its fits' (those of a request it explained); the
    # radii are those of the same request in the room without the survey's scatter.
    scatter = AmplitudeError(noise_sd=2e-7, relative_sd=0.01, dof=300.0)
    silent = replace(paper_room, amplitude_error=scatter)
    clean = true_amplitudes(silent, np.array([[1.3, 2.6], [2.9, 0.8], [0.7, 0.9]]))
    rng = np.random.default_rng(6)
    amplitudes = clean * (1.0 + 5 * scatter.relative_sd * rng.standard_normal(clean.shape))
    solver = GridlessSolver(build_fingerprint(silent), "correlation")
    verdicts = _recorded_verdicts(monkeypatch)
    answer = solver.solve_terminals(amplitudes)
    assert verdicts == [False]
    uncalibrated = GridlessSolver(build_fingerprint(paper_room), "correlation")
    own = uncalibrated.solve_terminals(amplitudes)
    monkeypatch.setattr(terminal_solve, "scatter_explains", lambda *_, **__: True)
    surveyed = solver.solve_terminals(amplitudes)
    np.testing.assert_array_equal(answer.positions, surveyed.positions)
    assert not np.allclose(answer.positions, own.positions, rtol=0, atol=1e-6)
    assert answer.covariances is not None and own.covariances is not None
    np.testing.assert_allclose(answer.covariances, own.covariances, rtol=1e-9)


def test_terminals_too_few_residuals_to_estimate_their_own_variances_keep_the_scatter(
    paper_room: Layout, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A room of five LEDs (four corners and one inside): each terminal leaves 2 residual
    # degrees of freedom, too few for its own variances. Amplitudes scattered ten times as
    # widely as the survey measured are answered as a level layout answers them (the
    # scatter's weights and radii), not with radii from their own two residuals.
    scatter = AmplitudeError(noise_sd=2e-7, relative_sd=0.01, dof=300.0)
    five = replace(
        paper_room,
        leds=tuple(paper_room.leds[i] for i in (0, 3, 5, 12, 15)),
        amplitude_error=scatter,
    )
    level = replace(five, grid=replace(five.grid, receivers_level=True))
    clean = true_amplitudes(five, np.array([[1.3, 2.6], [2.9, 0.8], [0.7, 0.9]]))
    rng = np.random.default_rng(6)
    amplitudes = clean * (1.0 + 10 * scatter.relative_sd * rng.standard_normal(clean.shape))
    solver = GridlessSolver(build_fingerprint(five), "correlation")
    answer = solver.solve_terminals(amplitudes)
    declared = GridlessSolver(build_fingerprint(level), "correlation").solve_terminals(amplitudes)
    assert answer.covariances is not None and declared.covariances is not None
    np.testing.assert_allclose(answer.positions, declared.positions, rtol=1e-6)
    np.testing.assert_allclose(answer.covariances, declared.covariances, rtol=1e-4)
    # The scatter does not explain these residuals: with their own variances taken as
    # estimable, the radii would be theirs, and wider.
    verdicts = _recorded_verdicts(monkeypatch)
    monkeypatch.setattr(terminal_solve, "own_variances_estimable", lambda *_: True)
    own = solver.solve_terminals(amplitudes)
    assert verdicts == [False]
    assert own.covariances is not None
    own_radii = [confidence_radius(c) for c in own.covariances]
    radii = [confidence_radius(c) for c in answer.covariances]
    assert all(mine < theirs for mine, theirs in zip(radii, own_radii, strict=True))


def test_a_calibration_measures_the_surveys_noise_and_relative_error(paper_room: Layout) -> None:
    # A dense survey of a room exactly as laid out, every amplitude off by 5 % (relative)
    # and by a noise of 3 % of the mean amplitude: the calibration finds both.
    ticks = np.arange(0.1, 4.0, 0.2)
    points = np.array([(x, y) for x in ticks for y in ticks])
    clean = true_amplitudes(paper_room, points)
    noise_sd = 0.03 * float(np.mean(clean))
    rng = np.random.default_rng(11)
    measured = clean * (1.0 + 0.05 * rng.standard_normal(clean.shape))
    measured = measured + noise_sd * rng.standard_normal(clean.shape)
    leds = np.broadcast_to(np.arange(paper_room.n_leds), clean.shape)
    rows = np.column_stack(
        (
            np.repeat(points, paper_room.n_leds, axis=0),
            leds.reshape(-1),
            measured.reshape(-1),
        )
    )
    result = calibrate(paper_room, survey_from_rows(rows), led_tilt_bound_deg=0.0)
    error = result.amplitude_error
    assert error is not None
    assert error.relative_sd == pytest.approx(0.05, rel=0.1)
    assert error.noise_sd == pytest.approx(noise_sd, rel=0.1)
    in_view = int(np.count_nonzero(clean > 0))
    assert 0.8 * in_view < error.dof < in_view
    # It travels with the calibrated layout (and its mapping) to the solver.
    layout = calibrated_layout(paper_room, result)
    assert layout.amplitude_error == error
    assert layout_from_mapping(layout.to_mapping()).amplitude_error == error


def test_a_layout_without_a_calibration_maps_as_before(paper_room: Layout) -> None:
    assert "amplitude_error" not in paper_room.to_mapping()
    assert layout_from_mapping(paper_room.to_mapping()).amplitude_error is None


def test_a_bad_amplitude_error_names_its_field(paper_room: Layout) -> None:
    mapping = paper_room.to_mapping()
    mapping["amplitude_error"] = {"noise_sd": 1.0, "relative_sd": -0.1, "dof": 10}
    with pytest.raises(GeometryError) as caught:
        layout_from_mapping(mapping)
    assert caught.value.field == "amplitude_error.relative_sd"
    mapping["amplitude_error"] = {"noise_sd": 1.0, "relative_sd": 0.1, "dof": 0}
    with pytest.raises(GeometryError) as caught:
        layout_from_mapping(mapping)
    assert caught.value.field == "amplitude_error.dof"
