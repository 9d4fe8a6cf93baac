"""A request's residuals estimate only the variances they hold degrees of freedom for
(:func:`app.vlp.solvers.gridless.uncertainty.estimable_misfit`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import AmplitudeError, Grid, Layout, Led, Room
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.solvers.gridless.uncertainty import estimable_misfit
from app.vlp.uncertainty import Misfit, MisfitDesign, fit_misfit, misfit_design_reference
from tests.terminal_information import position_covariance


def _design_and_residual(n_values: int, seed: int) -> tuple[MisfitDesign, np.ndarray]:
    # A fit of 3 parameters without priors (its residuals then hold n_values - 3 degrees of
    # freedom exactly), a tilt-like and a height-like model error of random columns.
    rng = np.random.default_rng(seed)
    jacobian = rng.standard_normal((n_values, 3))
    columns = [rng.standard_normal((n_values, 2)), rng.standard_normal((n_values, 1))]
    design = misfit_design_reference(jacobian, jacobian.T @ jacobian, columns)
    data = rng.standard_normal(n_values) + 2.0 * columns[0][:, 0]
    hat = jacobian @ np.linalg.solve(jacobian.T @ jacobian, jacobian.T)
    return design, data - hat @ data


@pytest.mark.parametrize("noise_estimated", [False, True], ids=["noise known", "noise fitted"])
def test_five_residuals_of_three_parameters_estimate_no_model_error(
    noise_estimated: bool,
) -> None:
    design, residual = _design_and_residual(5, seed=1)
    misfit = fit_misfit([design], [residual], noise=None if noise_estimated else 1.0)
    assert np.any(misfit.model_errors > 0)  # the moment fit put something on them
    estimable = estimable_misfit(misfit, [design], [residual], noise_estimated)
    np.testing.assert_array_equal(estimable.model_errors, 0.0)
    if noise_estimated:
        # All of the residual is the noise's, on its 5 - 3 degrees of freedom.
        assert estimable.noise == pytest.approx(float(residual @ residual) / 2.0)
        assert estimable.dofs[0] == pytest.approx(2.0)
    else:
        assert estimable.noise == misfit.noise


def test_residuals_without_a_degree_of_freedom_for_the_noise_are_left_as_they_are() -> None:
    # 3 values, 3 parameters (a room of two or three LEDs): nothing to estimate a noise
    # from. Whatever the moment fit said is returned as it is (the covariance then rests on
    # nothing and is bounded as such), not divided by zero degrees of freedom.
    design, residual = _design_and_residual(3, seed=3)
    assert float(np.sum(design.noise_leverage)) < 1.0
    fitted = Misfit(0.7, np.array([0.2, 0.3]), np.array([0.0, 0.5, 0.5]))
    assert estimable_misfit(fitted, [design], [residual], True) is fitted


def test_residuals_with_degrees_of_freedom_to_spare_keep_their_estimates() -> None:
    design, residual = _design_and_residual(16, seed=2)
    misfit = fit_misfit([design], [residual])
    assert np.any(misfit.model_errors > 0)
    assert estimable_misfit(misfit, [design], [residual], True) is misfit


def test_a_terminal_of_five_leds_in_a_calibrated_room_gets_the_scatters_radius() -> None:
    # Five LEDs, a room exactly as laid out, the survey's scatter known: one level terminal
    # (the layout does not say so) whose height is not sent. Its 5 - 3 residual degrees of
    # freedom cannot estimate its tilt's and height's variances, so its covariance is the
    # inverse of the weighted fit's information of its position and gain (the gain held at
    # 1, its uncertainty that of the gain's prior), computed here by central differences of
    # the simulator's channel.
    spots = [(1.0, 1.2), (3.6, 0.9), (1.3, 4.1), (3.9, 3.8), (2.4, 2.3)]
    noise_sd = 3e-7  # 4 % of the mean amplitude: above the fit's relative variance floor
    layout = Layout(
        room=Room(5.0, 5.0, 2.8),
        grid=Grid(0.1, 0.8),
        leds=tuple(Led(x=x, y=y, z=2.8, half_power_angle_deg=60.0) for x, y in spots),
        name="five LEDs",
        amplitude_error=AmplitudeError(noise_sd=noise_sd, relative_sd=0.0, dof=1e9),
    )
    solver = GridlessSolver(build_fingerprint(layout), "correlation")
    clean = true_amplitudes(layout, np.array([[2.1, 2.9]]))
    # A draw whose residuals the moment fit reads as a tilt and a height by chance (without
    # the rule its variance came out 1,000 times this one: a radius 30 times too wide).
    amplitudes = clean + noise_sd * np.random.default_rng(3).standard_normal(clean.shape)
    solution = solver.solve_terminals(amplitudes)
    assert solution.covariances is not None and solution.gains is not None
    gain = float(solution.gains[0])
    expected = position_covariance(layout, solution.positions[0], gain, noise_sd)
    np.testing.assert_allclose(solution.covariances[0], expected, rtol=5e-3)
    # A layout that declares its terminals' tilt spread still has it in the radius.
    spread = replace(layout, grid=replace(layout.grid, receiver_tilt_sd=3.0))
    wider = GridlessSolver(build_fingerprint(spread), "correlation").solve_terminals(amplitudes)
    assert wider.covariances is not None
    assert np.trace(wider.covariances[0]) > 1.5 * np.trace(solution.covariances[0])
