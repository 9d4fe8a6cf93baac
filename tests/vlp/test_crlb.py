"""Cramér-Rao bounds against closed forms, numeric Jacobians and Monte-Carlo estimates."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from app.vlp.channel import channel_gains, lambertian_order
from app.vlp.crlb import aggregated_correlation_covariance, aggregated_crlb, single_target_crlb
from app.vlp.errors import GeometryError, MeasurementError
from app.vlp.fingerprints import Fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import vech
from app.vlp.simulation import noise_std_for_snr


def _closed_form_bound(layout: Layout, point: np.ndarray, sigma: float) -> float:
    """(m+3)^2 sum_i SNR_i (p - s_i)(p - s_i)^T / d_i^4 with SNR_i = (h_i x_i)^2 / sigma^2."""
    gains = channel_gains(layout, point[None, :])[:, 0] * layout.pilot_amplitudes
    fisher = np.zeros((2, 2))
    for i, led in enumerate(layout.leds):
        if gains[i] == 0:
            continue
        m = float(lambertian_order(led.half_power_angle_deg))
        offset = point - np.array([led.x, led.y])
        d2 = offset @ offset + (led.z - layout.grid.receiver_height) ** 2
        fisher += (m + 3) ** 2 * gains[i] ** 2 / sigma**2 * np.outer(offset, offset) / d2**2
    return float(np.sqrt(np.trace(np.linalg.inv(fisher))))


@pytest.mark.parametrize(
    "point", [(2.0, 2.0), (0.3, 3.1), (1.7, 0.9)], ids=["centre", "corner", "off-centre"]
)
def test_single_target_matches_closed_form_bound(
    paper_room: Layout, point: tuple[float, float]
) -> None:
    p = np.array(point)
    assert single_target_crlb(paper_room, p, 1e-7) == pytest.approx(
        _closed_form_bound(paper_room, p, 1e-7), rel=1e-10
    )


def test_single_target_mixed_room_and_scaling(mixed_room: Layout) -> None:
    p = np.array([1.4, 1.1])
    bound = single_target_crlb(mixed_room, p, 1e-7)
    assert bound == pytest.approx(_closed_form_bound(mixed_room, p, 1e-7), rel=1e-10)
    # The bound is proportional to the noise standard deviation.
    assert single_target_crlb(mixed_room, p, 3e-7) == pytest.approx(3 * bound, rel=1e-12)


def test_single_target_bound_is_reached_by_maximum_likelihood(
    paper_room: Layout, paper_fingerprint: Fingerprint, rng: np.random.Generator
) -> None:
    sigma = noise_std_for_snr(paper_fingerprint, 40.0)
    truth = np.array([1.37, 2.61])
    clean = channel_gains(paper_room, truth[None, :])[:, 0] * paper_room.pilot_amplitudes
    scale = float(np.max(clean))

    def residual(p: np.ndarray, observed: np.ndarray) -> np.ndarray:
        model = channel_gains(paper_room, p[None, :])[:, 0] * paper_room.pilot_amplitudes
        return np.asarray((model - observed) / scale)

    errors = []
    for _ in range(300):
        observed = clean + sigma * rng.standard_normal(clean.shape)
        fit = least_squares(residual, truth, args=(observed,), method="lm", xtol=1e-12)
        errors.append(fit.x - truth)
    rmse = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))
    bound = single_target_crlb(paper_room, truth, sigma)
    assert rmse == pytest.approx(bound, rel=0.15)


def test_aggregated_single_target_equals_single_target_bound(
    paper_room: Layout, paper_fingerprint: Fingerprint
) -> None:
    # R = a a^T determines a up to its sign: at 30 dB the information is the same.
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    p = np.array([[2.3, 0.7]])
    single = single_target_crlb(paper_room, p[0], sigma)
    agg = aggregated_crlb(paper_room, p, sigma, noise_power_known=True)
    assert agg.mean == pytest.approx(single, rel=1e-3)
    assert aggregated_crlb(paper_room, p, sigma).mean >= agg.mean * (1 - 1e-12)


def test_covariance_formula_matches_monte_carlo(
    mixed_room: Layout, rng: np.random.Generator
) -> None:
    points = np.array([[0.9, 0.6], [2.2, 1.5]])
    gains = (channel_gains(mixed_room, points) * mixed_room.pilot_amplitudes[:, None]).T
    sigma = 0.5 * float(np.mean(np.abs(gains)))  # low SNR: the n n^T term matters
    draws = 40_000
    noise = sigma * rng.standard_normal((draws, 2, mixed_room.n_leds))
    amps = gains[None] + noise
    upper = np.triu_indices(mixed_room.n_leds)
    samples = np.einsum("dki,dkl->dil", amps, amps)[:, upper[0], upper[1]]
    empirical = np.cov(samples, rowvar=False)
    formula = aggregated_correlation_covariance(gains.T @ gains, sigma**2, 2)
    np.testing.assert_allclose(formula, empirical, rtol=0, atol=0.03 * np.max(formula))
    np.testing.assert_allclose(
        samples.mean(axis=0),
        vech(gains.T @ gains + 2 * sigma**2 * np.eye(5)),
        rtol=0,
        atol=0.02 * np.max(formula) ** 0.5,
    )


def _numeric_bound(layout: Layout, points: np.ndarray, sigma: float, model: str) -> np.ndarray:
    """Inverse Fisher from a central-difference Jacobian and an explicit covariance."""
    pilots = layout.pilot_amplitudes[:, None]

    def mean(flat: np.ndarray) -> np.ndarray:
        g = channel_gains(layout, flat.reshape(-1, 2)) * pilots
        return np.asarray(vech(g @ g.T) if model == "correlation" else (g**2).sum(axis=1))

    flat = points.ravel()
    step = 1e-6
    jac = np.column_stack(
        [(mean(flat + step * e) - mean(flat - step * e)) / (2 * step) for e in np.eye(flat.size)]
    )
    g = channel_gains(layout, points) * pilots
    k = points.shape[0]
    if model == "correlation":
        cov = aggregated_correlation_covariance(g @ g.T, sigma**2, k)
        atom = vech(np.eye(layout.n_leds))
    else:
        cov = np.diag(4 * sigma**2 * (g**2).sum(axis=1) + 2 * k * sigma**4)
        atom = np.ones(layout.n_leds)
    jac = np.column_stack([jac, atom])
    fisher = jac.T @ np.linalg.solve(cov, jac)
    return np.asarray(np.linalg.inv(fisher)[: 2 * k, : 2 * k])


@pytest.mark.parametrize("model", ["correlation", "power"])
def test_aggregated_bound_matches_numeric_jacobian(paper_room: Layout, model: str) -> None:
    points = np.array([[0.8, 1.1], [2.9, 3.3], [1.9, 2.0]])
    sigma = 2e-7
    bound = aggregated_crlb(paper_room, points, sigma, model)  # type: ignore[arg-type]
    expected = _numeric_bound(paper_room, points, sigma, model)
    np.testing.assert_allclose(bound.covariance, expected, rtol=1e-5)
    per_target = np.sqrt(np.diag(expected).reshape(3, 2).sum(axis=1))
    np.testing.assert_allclose(bound.per_target, per_target, rtol=1e-5)
    assert bound.mean == pytest.approx(float(per_target.mean()), rel=1e-5)


@pytest.mark.parametrize(
    "other", [(2.05, 2.02), (2.3, 2.2), (3.5, 0.5)], ids=["very-close", "close", "far"]
)
def test_a_second_target_never_helps_the_first(
    paper_room: Layout, paper_fingerprint: Fingerprint, other: tuple[float, float]
) -> None:
    # Its signal only adds noise (M0 grows) and its coordinates are extra unknowns.
    sigma = noise_std_for_snr(paper_fingerprint, 30.0)
    alone = aggregated_crlb(paper_room, np.array([[2.0, 2.0]]), sigma).per_target[0]
    pair = aggregated_crlb(paper_room, np.array([[2.0, 2.0], other]), sigma).per_target[0]
    assert pair >= alone


def test_bad_inputs(paper_room: Layout) -> None:
    with pytest.raises(MeasurementError):
        single_target_crlb(paper_room, np.array([1.0, 1.0]), 0.0)
    with pytest.raises(GeometryError):
        aggregated_crlb(paper_room, np.array([[5.0, 1.0]]), 1e-7)
    with pytest.raises(GeometryError):
        aggregated_crlb(paper_room, np.zeros((2, 3)), 1e-7)
    with pytest.raises(MeasurementError):
        aggregated_crlb(paper_room, np.ones((1, 2)), 1e-7, "amplitude")  # type: ignore[arg-type]
