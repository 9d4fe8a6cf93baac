"""Per-terminal fits: each terminal's own amplitudes locate it (solvers/gridless/terminals.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from app.vlp.channel import channel_gains, led_constants
from app.vlp.errors import MeasurementError
from app.vlp.fingerprints import Fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.simulation import noise_std_for_snr, random_positions, true_amplitudes
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from app.vlp.solvers.gridless.channel import ChannelKernel
from app.vlp.solvers.gridless.options import nuisance_priors
from app.vlp.solvers.gridless.terminal_weights import rewhitened, terminal_nll
from app.vlp.solvers.gridless.terminals import (
    _HELD_LOG_GAIN_SD,
    fit_terminal,
    los_with_normal,
)
from tests.vlp.test_gridless_nuisances import _matched


@pytest.fixture(scope="module")
def solver(paper_fingerprint: Fingerprint) -> GridlessSolver:
    return GridlessSolver(paper_fingerprint, "correlation")


def _direct_los(layout: Layout, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Paper eq. 1 LED by LED, with cos(alpha) and cos(phi) from the geometry."""
    orders, prefactors = led_constants(layout)
    fov = math.radians(layout.receiver.fov_deg)
    gains = []
    for led, order, prefactor in zip(layout.leds, orders, prefactors, strict=True):
        towards = np.array([led.x, led.y, led.z]) - point
        distance = float(np.linalg.norm(towards))
        cos_alpha = towards[2] / distance
        cos_phi = float(towards @ normal) / distance
        seen = cos_phi > 0 and math.acos(min(cos_phi, 1.0)) <= fov
        gains.append(prefactor * cos_alpha**order * cos_phi / distance**2 if seen else 0.0)
    return np.array(gains) * layout.pilot_amplitudes


def test_upward_normal_matches_the_channel_model(paper_room: Layout) -> None:
    kernel = ChannelKernel(paper_room, scale=1.0)
    points = random_positions(paper_room, 5, rng=2)
    expected = channel_gains(paper_room, points) * paper_room.pilot_amplitudes[:, None]
    for k, (x, y) in enumerate(points):
        gains, _ = los_with_normal(kernel, np.array([x, y, 0.85]), np.array([0.0, 0.0, 1.0]))
        np.testing.assert_allclose(gains, expected[:, k], rtol=1e-12)


@pytest.mark.parametrize("tilt_deg", [5.0, 20.0, 45.0])
def test_tilted_normal_matches_the_geometry_and_its_gradient(
    paper_room: Layout, tilt_deg: float
) -> None:
    kernel = ChannelKernel(paper_room, scale=1.0)
    tilt = math.radians(tilt_deg)
    normal = np.array([math.sin(tilt) * math.cos(0.3), math.sin(tilt) * math.sin(0.3), 0.0])
    normal[2] = math.cos(tilt)
    point = np.array([1.3, 2.6, 1.1])
    gains, gradient = los_with_normal(kernel, point, normal)
    np.testing.assert_allclose(gains, _direct_los(paper_room, point, normal), rtol=1e-12)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = 1e-6
        ahead = los_with_normal(kernel, point + step, normal)[0]
        behind = los_with_normal(kernel, point - step, normal)[0]
        inside = (ahead > 0) & (behind > 0)
        np.testing.assert_allclose(
            gradient[inside, axis], ((ahead - behind) / 2e-6)[inside], rtol=1e-5, atol=1e-12
        )


def test_noiseless_terminals_with_gains_heights_and_tilts_are_recovered_exactly(
    paper_room: Layout, solver: GridlessSolver
) -> None:
    truth = np.array([[0.7, 1.2], [2.9, 3.3], [2.2, 0.4]])
    heights = np.array([0.8, 1.2, 0.85])
    tilt = math.radians(12.0)
    normals = np.array(
        [
            [0.0, 0.0, 1.0],
            [math.sin(tilt), 0.0, math.cos(tilt)],
            [0.0, -math.sin(tilt), math.cos(tilt)],
        ]
    )
    gains = np.array([1.0, 0.8, 1.3])
    amplitudes = np.array(
        [
            gains[k] * _direct_los(paper_room, np.array([*truth[k], heights[k]]), normals[k])
            for k in range(3)
        ]
    )
    solution = solver.solve_terminals(amplitudes, heights, normals)
    # Noiseless, only the gain prior (sd 0.1 in log) pulls a 1.3x terminal: sub-millimetre.
    np.testing.assert_allclose(solution.positions, truth, atol=1e-3)
    assert solution.gains is not None
    np.testing.assert_allclose(solution.gains, gains, rtol=1e-2)
    level = GridlessSolver(solver.fingerprint, "correlation", GridlessOptions(tilt_sd=None))
    upright = level.solve_terminals(amplitudes, heights)  # tilts ignored: centimetres off
    assert np.abs(upright.positions - truth).max() > 0.01
    assert solution.heights is not None
    np.testing.assert_allclose(solution.heights, heights)


def test_each_terminal_alone_beats_their_aggregate(
    paper_room: Layout, paper_fingerprint: Fingerprint, solver: GridlessSolver
) -> None:
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    rng = np.random.default_rng(8)
    alone, pooled = [], []
    for _ in range(12):
        truth = random_positions(paper_room, 8, rng=rng)
        amplitudes = true_amplitudes(paper_room, truth) + sigma * rng.standard_normal((8, 16))
        each = solver.solve_terminals(amplitudes)
        # Labels are known: estimate k is terminal k's.
        alone.append(float(np.mean(np.linalg.norm(each.positions - truth, axis=1))))
        aggregate = measurement_from_amplitudes(amplitudes, "correlation", 16)
        pooled.append(float(np.mean(_matched(truth, solver.solve(aggregate, 8).positions)[1])))
    # The single-terminal Cramer-Rao bound here is about 2.3 cm; the aggregate's at K = 8
    # about 5.4 cm (docs/results/accuracy.md).
    assert np.mean(alone) < 0.04
    assert np.mean(alone) < np.mean(pooled)


def test_amplitudes_a_thousand_times_too_large_are_refused(
    paper_room: Layout, solver: GridlessSolver
) -> None:
    amplitudes = 1000 * true_amplitudes(paper_room, np.array([[1.0, 1.0], [3.0, 2.0]]))
    with pytest.raises(MeasurementError, match="larger than any point") as caught:
        solver.solve_terminals(amplitudes)
    assert caught.value.field == "terminals"
    flagged = solver.solve_terminals(amplitudes / 100)  # 10x: answered, flagged
    assert flagged.fit is not None and flagged.fit.quality == "scale_mismatch"


def test_an_unknown_tilt_is_fitted_when_it_matters(
    paper_room: Layout, paper_fingerprint: Fingerprint, solver: GridlessSolver
) -> None:
    # Hand-held phones: polar tilt uniform in [0, 20] deg, any azimuth, normals not sent.
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    rng = np.random.default_rng(21)
    level = GridlessSolver(paper_fingerprint, "correlation", GridlessOptions(tilt_sd=None))
    fitted, ignored = [], []
    for _ in range(3):
        truth = random_positions(paper_room, 8, rng=rng)
        polar = np.radians(rng.uniform(0.0, 20.0, 8))
        azimuth = rng.uniform(0.0, 2.0 * math.pi, 8)
        normals = np.column_stack(
            (np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar))
        )
        amplitudes = np.array(
            [_direct_los(paper_room, np.array([*truth[k], 0.85]), normals[k]) for k in range(8)]
        )
        amplitudes = amplitudes + sigma * rng.standard_normal(amplitudes.shape)
        fitted += list(np.linalg.norm(solver.solve_terminals(amplitudes).positions - truth, axis=1))
        ignored += list(np.linalg.norm(level.solve_terminals(amplitudes).positions - truth, axis=1))
    assert np.mean(fitted) < 0.8 * np.mean(ignored)


def test_a_gain_as_modelled_is_held_and_a_different_one_is_fitted(
    paper_room: Layout, paper_fingerprint: Fingerprint, solver: GridlessSolver
) -> None:
    # A free gain trades against the distance to the brightest LEDs: held at 1 where the data
    # do not ask for more, fitted where they do.
    rng = np.random.default_rng(31)
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    truth = random_positions(paper_room, 8, distinct_cells=True, rng=rng)
    true_gains = np.ones(8)
    true_gains[[2, 5]] = [0.8, 1.25]
    amplitudes = true_gains[:, None] * true_amplitudes(paper_room, truth)
    amplitudes = amplitudes + sigma * rng.standard_normal(amplitudes.shape)
    solution = solver.solve_terminals(amplitudes)
    assert solution.gains is not None
    np.testing.assert_allclose(solution.gains[[2, 5]], [0.8, 1.25], rtol=0.03)
    held = np.abs(solution.gains[true_gains == 1.0] - 1.0) < 1e-4
    assert int(held.sum()) >= 4  # by chance a test at 2 frees about 1 gain in 6
    errors = np.linalg.norm(solution.positions - truth, axis=1)
    assert errors.max() < 0.1


def test_a_held_gain_keeps_the_gain_uncertainty_in_the_covariance(paper_room: Layout) -> None:
    # Held at 1, the gain still may be off by what its test cannot see: the position's
    # covariance is that of the gain with its own prior, not of a gain known exactly.
    kernel = ChannelKernel(paper_room, scale=1.0)
    priors = nuisance_priors(paper_room, GridlessOptions())
    assert priors.log_gain_sd is not None
    point = np.array([[0.3, 0.3]])  # near a corner the gain and the distance trade off most
    clean = true_amplitudes(paper_room, point)[0]
    sigma = 0.01 * float(np.sqrt(np.mean(clean**2)))
    amplitudes = clean + sigma * np.random.default_rng(4).standard_normal(clean.shape)
    fit = fit_terminal(
        kernel, amplitudes, point, priors=priors, sigma2=sigma**2, height=None, normal=None
    )
    assert abs(fit.log_gain) < 1e-5  # held
    # The same fit with the gain free (no hold possible: its prior is wide).
    free = fit_terminal(
        kernel,
        amplitudes,
        point,
        priors=replace(priors, log_gain_sd=None),
        sigma2=sigma**2,
        height=None,
        normal=None,
    )
    held_cov = np.linalg.inv(fit.normal)[:2, :2]
    free_normal = free.normal.copy()
    free_normal[-1, -1] += 1.0 / priors.log_gain_sd**2  # the free fit with the prior's information
    free_cov = np.linalg.inv(free_normal)[:2, :2]
    np.testing.assert_allclose(np.trace(held_cov), np.trace(free_cov), rtol=0.05)
    # What the holding prior itself would give: about half (a gain known exactly).
    holding = fit.normal.copy()
    holding[-1, -1] += 1.0 / _HELD_LOG_GAIN_SD**2 - 1.0 / priors.log_gain_sd**2
    assert np.trace(held_cov) > 1.5 * np.trace(np.linalg.inv(holding)[:2, :2])


def test_a_held_gain_fit_never_ends_above_its_start(paper_room: Layout) -> None:
    # Three LEDs and terminals 2-3 times brighter than modelled: the start's least-squares
    # gain lies far out in a held gain's prior, and a fit started there once walked to the
    # room's corners. Held at 1, LM must end no worse than the start itself (gain 1).
    layout = replace(paper_room, leds=tuple(paper_room.leds[i] for i in (0, 5, 10)))
    kernel = ChannelKernel(layout, scale=1.0)
    priors = replace(nuisance_priors(layout, GridlessOptions()), log_gain_sd=_HELD_LOG_GAIN_SD)
    for x, y, gain in [(0.6, 0.6, 3.0), (1.0, 1.0, 2.0), (1.0, 1.8, 3.0), (2.2, 1.4, 0.5)]:
        start = np.array([[x, y]])
        amplitudes = gain * true_amplitudes(layout, start)[0]
        sigma2 = (0.01 * float(np.sqrt(np.mean(amplitudes**2)))) ** 2
        fit = fit_terminal(
            kernel, amplitudes, start, priors=priors, sigma2=sigma2, height=None, normal=None
        )
        modelled = layout.pilot_amplitudes * channel_gains(layout, start)[:, 0]
        at_start = float(np.sum((amplitudes - modelled) ** 2))
        assert abs(fit.log_gain) < 1e-4
        assert fit.rss <= at_start * (1.0 + 1e-9)


def test_rewhitening_a_fit_is_its_model_under_the_new_weights(paper_room: Layout) -> None:
    kernel = ChannelKernel(paper_room, scale=1.0)
    priors = nuisance_priors(paper_room, GridlessOptions())
    point = np.array([[1.1, 2.3]])
    amplitudes = 1.2 * true_amplitudes(paper_room, point)[0]
    amplitudes = amplitudes * (1 + 0.02 * np.random.default_rng(5).standard_normal(16))
    sigma2 = (0.01 * float(np.sqrt(np.mean(amplitudes**2)))) ** 2
    fit = fit_terminal(
        kernel, amplitudes, point, priors=priors, sigma2=sigma2, height=None, normal=None
    )
    weight = np.linspace(0.5, 2.0, 16) / math.sqrt(sigma2)
    moved = rewhitened(fit, weight)
    modelled = math.exp(fit.log_gain) * _direct_los(
        paper_room, np.array([*fit.position, 0.85]), np.array([0.0, 0.0, 1.0])
    )
    np.testing.assert_allclose(moved.residual, weight * (amplitudes - modelled), rtol=1e-9)
    np.testing.assert_allclose(moved.jacobian[:, -1], weight * modelled, rtol=1e-9)
    # the priors' part of the cost and of the normal matrix is the fit's own
    assert moved.cost - moved.residual @ moved.residual == pytest.approx(
        fit.cost - fit.residual @ fit.residual, rel=1e-9, abs=1e-12
    )
    back = rewhitened(moved, fit.data_weight)
    np.testing.assert_allclose(back.normal, fit.normal, rtol=1e-9)
    np.testing.assert_allclose(back.residual, fit.residual, rtol=1e-9)


@pytest.mark.parametrize("tail_dof", [None, 2.5])
def test_a_terminal_nll_differs_from_scipy_densities_by_a_constant(
    paper_room: Layout, tail_dof: float | None
) -> None:
    kernel = ChannelKernel(paper_room, scale=1.0)
    priors = nuisance_priors(paper_room, GridlessOptions())
    rng = np.random.default_rng(8)
    nll, reference = [], []
    for point in ([1.1, 2.3], [3.2, 0.6]):
        clean = 1.3 * true_amplitudes(paper_room, np.array([point]))[0]
        amplitudes = clean * (1 + 0.05 * rng.standard_normal(16))
        sigma2 = (0.02 * float(np.sqrt(np.mean(amplitudes**2)))) ** 2
        fit = fit_terminal(
            kernel,
            amplitudes,
            np.array([point]),
            priors=priors,
            sigma2=sigma2,
            height=None,
            normal=None,
        )
        variances = sigma2 * np.linspace(0.5, 3.0, 16)
        residual = fit.residual / fit.data_weight
        scales = np.sqrt(variances)
        if tail_dof is None:
            log_density = stats.norm.logpdf(residual, scale=scales)
        else:
            log_density = stats.t.logpdf(residual, tail_dof, scale=scales)
        prior = 0.5 * (fit.cost - fit.residual @ fit.residual)
        nll.append(terminal_nll(fit, variances, tail_dof))
        reference.append(-float(np.sum(log_density)) + prior)
    # the same constant for both: differences agree
    assert nll[0] - nll[1] == pytest.approx(reference[0] - reference[1], rel=1e-9)
