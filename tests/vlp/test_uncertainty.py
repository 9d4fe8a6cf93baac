"""Confidence radii and fit classification (app/vlp/uncertainty.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from app.vlp._kernels import KERNELS, KernelMode, use_kernels
from app.vlp.radii import bounded_covariances, confidence_radii, confidence_radius
from app.vlp.uncertainty import (
    NOISE_ONLY_P,
    POOR_FIT_CHI2,
    SCALE_MISMATCH_FACTOR,
    Misfit,
    assess_fit,
    f2_widening,
    fit_misfit,
    misfit_design_reference,
    own_excess_widening,
    predictive_covariances,
)


@pytest.mark.parametrize("sigma", [1e-3, 0.05, 2.0])
@pytest.mark.parametrize("level", [0.5, 0.95, 0.99])
def test_isotropic_radius_is_the_rayleigh_quantile(sigma: float, level: float) -> None:
    # |e| of an isotropic 2-D Gaussian is Rayleigh: P(|e| <= r) = 1 - exp(-r^2 / (2 sigma^2)).
    expected = sigma * math.sqrt(-2.0 * math.log(1.0 - level))
    radius = confidence_radius(np.eye(2) * sigma**2, level)
    assert radius == pytest.approx(expected, rel=1e-9)


def test_a_degenerate_ellipse_tends_to_the_one_dimensional_quantile() -> None:
    # All the variance along one rotated axis: |e| = |N(0, s^2)|, 95 % at 1.959964 s.
    direction = np.array([math.cos(0.7), math.sin(0.7)])
    covariance = 0.04 * np.outer(direction, direction) + 1e-14 * np.eye(2)
    assert confidence_radius(covariance) == pytest.approx(1.959964 * 0.2, rel=1e-5)


def test_radius_matches_monte_carlo_for_a_correlated_ellipse() -> None:
    covariance = np.array([[0.03, 0.012], [0.012, 0.01]])
    radius = confidence_radius(covariance)
    draws = np.random.default_rng(7).multivariate_normal([0.0, 0.0], covariance, 400_000)
    inside = float(np.mean(np.linalg.norm(draws, axis=1) <= radius))
    assert inside == pytest.approx(0.95, abs=0.002)  # 5 binomial standard errors


def test_radius_is_invariant_under_rotation() -> None:
    covariance = np.array([[0.02, 0.0], [0.0, 0.005]])
    angle = 1.1
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    rotated = rotation @ covariance @ rotation.T
    assert confidence_radius(rotated) == pytest.approx(confidence_radius(covariance), rel=1e-9)


def _coverage(covariance: np.ndarray, radius: float) -> float:
    """P(|e| <= radius) by adaptive quadrature over the major axis, independent of the
    solver's Gauss-Legendre rule and Newton steps."""
    minor, major = np.linalg.eigvalsh(covariance)
    reach = radius / math.sqrt(major)

    def slice_probability(x: float) -> float:
        left = max(radius**2 - major * x**2, 0.0)
        inner = 2.0 * special.ndtr(math.sqrt(left / minor)) - 1.0
        return float(math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi) * inner)

    value, _ = integrate.quad(slice_probability, -reach, reach, epsabs=1e-13, limit=400)
    return float(value)


@pytest.mark.parametrize("ratio", [1.0, 0.5, 0.1, 1e-2, 1e-3, 1e-5, 1e-8])
@pytest.mark.parametrize("level", [0.5, 0.95])
def test_radii_hold_their_level_for_any_elongation(ratio: float, level: float) -> None:
    angle = 0.4
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    covariance = rotation @ np.diag([0.02, 0.02 * ratio]) @ rotation.T
    radius = confidence_radius(covariance, level)
    # The 96-point rule resolves the probability to ~1e-5 at the worst elongations
    # (rho ~ 1e-4, where the inner term turns from 0 to 1 within a few nodes); that moves a
    # radius by ~1e-4 of itself, far below any estimate's uncertainty.
    assert _coverage(covariance, radius) == pytest.approx(level, abs=5e-5)


def test_radii_of_many_estimates_equal_each_alone() -> None:
    rng = np.random.default_rng(11)
    factors = rng.normal(size=(40, 2, 2))
    covariances = factors @ factors.transpose(0, 2, 1) * 10.0 ** rng.uniform(-6, 0, (40, 1, 1))
    covariances[3] = 0.0
    covariances[5, 0, 0] = np.nan
    covariances[7] = np.diag([0.01, 0.0])  # a degenerate ellipse: the 1-D quantile
    radii = confidence_radii(covariances)
    alone = [confidence_radius(covariance) for covariance in covariances]
    np.testing.assert_allclose(radii, alone, rtol=1e-12)
    assert radii[3] == 0.0 and math.isinf(radii[5])
    assert radii[7] == pytest.approx(1.959964 * 0.1, rel=1e-6)
    assert confidence_radii(np.zeros((0, 2, 2))).shape == (0,)
    with pytest.raises(ValueError, match="shape"):
        confidence_radii(np.eye(2))


@pytest.mark.parametrize("kernels", KERNELS)
def test_radii_of_covariances_that_say_nothing(kernels: KernelMode) -> None:
    covariances = np.array(
        [
            np.full((2, 2), np.nan),
            [[np.inf, 0.0], [0.0, 1e-4]],
            [[1e-4, np.inf], [np.inf, 1e-4]],
            np.zeros((2, 2)),
            np.diag([0.01, 0.0]),
            -1e-4 * np.eye(2),
        ]
    )
    with use_kernels(kernels):
        radii = confidence_radii(covariances)
    assert np.isinf(radii[:3]).all()
    assert radii[3] == 0.0 and radii[5] == 0.0
    assert radii[4] == pytest.approx(1.959964 * 0.1, rel=1e-6)


def test_the_compiled_eigenvalues_are_lapacks() -> None:
    """The radii kernel's eigenvalues of a symmetric 2 x 2 matrix in closed form are those
    of numpy's eigvalsh (LAPACK), bit for bit: diagonal and nearly diagonal ones too."""
    from app.vlp._radii_compiled import _eigenvalues

    rng = np.random.default_rng(5)
    factors = rng.normal(size=(300, 2, 2))
    matrices = list(factors @ factors.transpose(0, 2, 1) * 10.0 ** rng.uniform(-10, 2, (300, 1, 1)))
    off = np.array([[0.0, 1.0], [1.0, 0.0]])
    matrices += [
        np.diag([3e-4, 1e-4]),
        np.zeros((2, 2)),
        np.full((2, 2), 1e-4),
        1e-4 * np.eye(2) + 1e-22 * off,
        np.diag([2.0, 1.0]) + 1e-17 * off,
        np.diag([2e-3, 1e-9]) + 3e-7 * off,
    ]
    for matrix in matrices:
        minor, major = np.linalg.eigvalsh(matrix)
        assert _eigenvalues(matrix[0, 0], matrix[1, 0], matrix[1, 1]) == (major, minor)


def test_fit_quality_classes() -> None:
    assert assess_fit(100.0, 100, 1.0).quality == "ok"
    poor = assess_fit(100.0 * (POOR_FIT_CHI2 + 1.0), 100, 1.0)
    assert poor.quality == "poor"
    assert poor.chi2_per_dof == pytest.approx(POOR_FIT_CHI2 + 1.0)
    for scale in (SCALE_MISMATCH_FACTOR * 1.01, 1.0 / (SCALE_MISMATCH_FACTOR * 1.01), 1000.0):
        mismatch = assess_fit(100.0, 100, scale)
        assert mismatch.quality == "scale_mismatch"
        assert "units" in mismatch.detail
    # A scale mismatch is reported before a poor fit: it is the likelier cause.
    assert assess_fit(1e6, 100, 10.0).quality == "scale_mismatch"


@pytest.mark.parametrize("dof", [10, 30, 110, 1000])
def test_only_noise_is_said_to_be_explained_to_its_noise(dof: int) -> None:
    """Chi-squares of pure noise (sums of ``dof`` squared standard normals) are said to be
    explained to the noise nearly always (chance 1 - NOISE_ONLY_P); one of 2.5x its expected
    value at 110 degrees of freedom (a gain 3 sd off its prior, K = 8) is answered ``ok``
    but says the room differs from its layout."""
    rng = np.random.default_rng(dof)
    draws = np.sum(rng.standard_normal((4000, dof)) ** 2, axis=1)
    said_noise = [
        assess_fit(float(chi2), dof, 1.0).detail.endswith("to its noise") for chi2 in draws
    ]
    assert np.mean(said_noise) >= 0.995
    if dof >= 30:
        off = assess_fit(2.5 * dof, dof, 1.0)
        assert off.quality == "ok"
        assert "2.5x the expected residual" in off.detail
        assert "differs a little from its layout" in off.detail


def _linear_problem(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A whitened linear fit: Jacobian (L = 60, P = 4, the last with a unit Gaussian prior),
    its normal matrix, and model-error columns F (60, 60) scaled like a signal."""
    rng = np.random.default_rng(seed)
    jacobian = rng.standard_normal((60, 4))
    prior = np.diag([0.0, 0.0, 0.0, 1.0])
    signal = np.abs(rng.standard_normal(60)) * 2.0
    return jacobian, jacobian.T @ jacobian + prior, np.diag(signal)


def test_misfit_design_leverages_equal_the_explicit_projections() -> None:
    jacobian, normal, errors = _linear_problem(1)
    design = misfit_design_reference(jacobian, normal, [errors])
    residual_map = np.eye(60) - jacobian @ np.linalg.inv(normal) @ jacobian.T  # Q
    assert np.allclose(design.noise_leverage, np.diag(residual_map @ residual_map.T))
    seen = residual_map @ errors
    assert np.allclose(design.error_leverages[:, 0], np.diag(seen @ seen.T))
    assert design.error_spread[0] == pytest.approx(np.trace((seen @ seen.T) @ (seen @ seen.T)))


def test_sandwich_covariance_matches_monte_carlo_of_the_estimator() -> None:
    # theta_hat - theta = A (J^T (n + F d) + prior pseudo-noise): its covariance is the sandwich.
    jacobian, normal, errors = _linear_problem(2)
    design = misfit_design_reference(jacobian, normal, [errors])
    inverse = np.linalg.inv(normal)
    rng = np.random.default_rng(3)
    draws = 40_000
    noise = rng.standard_normal((draws, 60))
    model = rng.standard_normal((draws, 60)) * math.sqrt(0.04)
    prior_noise = np.zeros((draws, 4))
    prior_noise[:, 3] = rng.standard_normal(draws)
    deviations = (noise + model @ errors.T) @ jacobian @ inverse.T + prior_noise @ inverse.T
    empirical = np.cov(deviations.T)
    expected = design.covariance(1.0, np.array([0.04]))
    # 40 000 draws: each entry within a few % of the diagonal scale.
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.all(np.abs(empirical - expected) <= 0.05 * scale)


@pytest.mark.parametrize("model_error", [0.0, 0.05])
def test_fitted_misfit_gives_honest_95_percent_regions(model_error: float) -> None:
    # Residuals of a linear fit with a signal-proportional model error of variance b: the
    # moment estimate of b, widened for its degrees of freedom, makes the 95 % ellipse of
    # the first two parameters hold the truth about 95 % of the time; noise alone (b = 0)
    # stays about 95 % too, not inflated to near 100 %.
    jacobian, normal, errors = _linear_problem(4)
    design = misfit_design_reference(jacobian, normal, [errors])
    inverse = np.linalg.inv(normal)
    residual_map = np.eye(60) - jacobian @ inverse @ jacobian.T
    rng = np.random.default_rng(5)
    inside = []
    fitted = []
    for _ in range(2000):
        error = rng.standard_normal(60) + errors @ rng.standard_normal(60) * math.sqrt(model_error)
        misfit = fit_misfit([design], [residual_map @ error], noise=1.0)
        fitted.append(misfit.model_errors[0])
        covariance = predictive_covariances(design, misfit, np.array([[0, 1]]))[0]
        deviation = (inverse @ jacobian.T @ error)[:2]
        inside.append(float(deviation @ np.linalg.solve(covariance, deviation)) <= 5.991)
    # 2000 draws: a binomial standard error of 0.005 at 0.95; the bounds are 5 of them wide
    # of what the method gives (0.944 and 0.959 here: the non-negative estimate and the
    # Satterthwaite degrees of freedom are approximations).
    assert 0.92 <= float(np.mean(inside)) <= 0.98
    if model_error > 0.0:
        assert float(np.mean(fitted)) == pytest.approx(model_error, rel=0.25)


def test_a_fit_whose_own_residual_the_pooled_variances_do_not_explain_is_widened() -> None:
    # Pooled variances (noise 1, a signal-proportional model error 0.02): residuals drawn
    # from them are seldom widened; one whose square sum is past the 1 - NOISE_ONLY_P
    # quantile of its Satterthwaite chi-square (computed here with explicit projections and
    # scipy.stats) is widened by its Birge ratio times the F widening of those dof.
    jacobian, normal, errors = _linear_problem(6)
    design = misfit_design_reference(jacobian, normal, [errors])
    misfit = Misfit(1.0, np.array([0.02]), np.array([math.inf, 40.0]))
    residual_map = np.eye(60) - jacobian @ np.linalg.inv(normal) @ jacobian.T  # Q
    seen = residual_map @ errors
    expected_squares = np.diag(residual_map @ residual_map.T) + 0.02 * np.diag(seen @ seen.T)
    expected = float(expected_squares.sum())
    dof = expected**2 / float(np.sum(expected_squares**2))
    threshold = expected * float(stats.chi2.isf(NOISE_ONLY_P, dof)) / dof
    rng = np.random.default_rng(8)
    widened = 0
    for _ in range(4000):
        error = rng.standard_normal(60) + errors @ rng.standard_normal(60) * math.sqrt(0.02)
        widened += own_excess_widening(design, residual_map @ error, misfit) > 1.0
    # Nominally 0.1 % (4 of 4000); the Satterthwaite approximation may move that a little.
    assert widened <= 40
    direction = residual_map @ rng.standard_normal(60)
    direction /= np.linalg.norm(direction)
    below = direction * math.sqrt(threshold * (1.0 - 1e-6))
    assert own_excess_widening(design, below, misfit) == 1.0
    above = direction * math.sqrt(threshold * (1.0 + 1e-6))
    expected_factor = threshold * (1.0 + 1e-6) / expected * f2_widening(np.array([dof]))[0]
    assert own_excess_widening(design, above, misfit) == pytest.approx(expected_factor, rel=1e-9)
    assert expected_factor > 1.5  # a fit past the quantile is widened by much, not by a hair


def test_f2_widening_is_the_f_over_chi_square_quantile_ratio() -> None:
    dof = np.array([0.5, 1.0, 2.0, 3.7, 10.0, 100.0, 1e4, 1e9])
    for level in (0.5, 0.95, 0.99):
        expected = 2.0 * stats.f.ppf(level, 2, dof) / stats.chi2.ppf(level, 2)
        np.testing.assert_allclose(f2_widening(dof, level), expected, rtol=1e-9)
    assert f2_widening(np.array([1e15]))[0] == pytest.approx(1.0, abs=1e-9)
    # Next to no degrees of freedom: infinitely wide, without an overflow warning (a random
    # room's answer raised one; the suite turns warnings into errors).
    assert f2_widening(np.array([1e-3]))[0] == np.inf
    assert f2_widening(np.array([0.0]))[0] == np.inf


def test_bounded_covariances_cap_the_radius_and_keep_the_shape() -> None:
    rotation = np.array([[math.cos(0.4), -math.sin(0.4)], [math.sin(0.4), math.cos(0.4)]])
    wide = rotation @ np.diag([9.0, 1.0]) @ rotation.T  # a 95 % radius of several metres
    small = np.eye(2) * 1e-4
    singular = np.full((2, 2), np.inf)
    bounded = bounded_covariances(np.array([wide, small, singular]), 2.0)
    radii = confidence_radii(bounded)
    assert radii[0] == pytest.approx(2.0, rel=1e-9)
    # Scaled as a whole: the same eigenvectors and the same 9:1 elongation.
    values, vectors = np.linalg.eigh(bounded[0])
    assert values[1] / values[0] == pytest.approx(9.0, rel=1e-9)
    assert abs(vectors[:, 1] @ rotation[:, 0]) == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_array_equal(bounded[1], small)
    # Non-finite: the isotropic circle of that radius, 2 = s sqrt(-2 ln 0.05).
    s = 2.0 / math.sqrt(-2.0 * math.log(0.05))
    np.testing.assert_allclose(bounded[2], s**2 * np.eye(2), rtol=1e-12)
    with pytest.raises(ValueError, match="max_radius"):
        bounded_covariances(np.array([small]), 0.0)


def test_bounded_covariances_replace_what_is_no_covariance() -> None:
    """Computed in round-off (a singular information), a "covariance" can have a negative
    variance or opposite infinities; from a pseudo-inverse, a direction with no information
    at all gets 0 (a receiver that sees one LED: the ring's tangent "exact", found by a scan
    of random rooms). Neither says anything, so each becomes the circle of the largest
    radius, with no numpy warning (the suite turns warnings into errors)."""
    negative = np.array([[-6.5e37, -3.0e37], [-2.9e37, 3.7e37]])
    opposite = np.array([[-np.inf, -np.inf], [-np.inf, np.inf]])
    indefinite = np.array([[1.0, 2.0], [2.0, 1.0]])  # variances fine, determinant -3
    ring = np.array([[0.003, -0.003], [-0.003, 0.003]])  # rank 1: the tangent dropped
    zero = np.zeros((2, 2))  # a target where no LED is seen
    nearly_singular = np.array([[1.0, 1.0], [1.0, 1.0 + 1e-14]])  # sds 1e7 apart
    thin = np.array([[1.0, 1.0], [1.0, 1.0 + 1e-6]])  # sds 2000 apart: a valid thin ellipse
    small = np.eye(2) * 1e-4
    covariances = np.array([negative, opposite, indefinite, ring, zero, nearly_singular])
    bounded = bounded_covariances(np.concatenate((covariances, [thin, small])), 2.0)
    s = 2.0 / math.sqrt(-2.0 * math.log(0.05))
    for index in range(len(covariances)):
        np.testing.assert_allclose(bounded[index], s**2 * np.eye(2), rtol=1e-12)
    np.testing.assert_array_equal(bounded[-1], small)
    # The thin ellipse is kept, only scaled down to the radius.
    assert confidence_radii(bounded[-2:-1])[0] == pytest.approx(2.0, rel=1e-9)
    np.testing.assert_allclose(bounded[-2] / bounded[-2, 0, 0], thin, rtol=1e-12)
