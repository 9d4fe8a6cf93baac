"""The one Levenberg-Marquardt loop (``gridless/lm.py``) and its compiled twin
(``gridless/_compiled/lm.py``), on a small model of their own: a point located from its
ranges to six anchors, each range read with a common bias. The fits that run the loop on the
solver's models (aggregated, terminal, room tolerances) are compared with their references in
``test_compiled.py``.
"""

from __future__ import annotations

from typing import Any, NamedTuple, cast

import numba
import numpy as np
import pytest
from scipy import optimize
from scipy.linalg import lapack

from app.vlp.solvers.gridless._compiled.lm import (
    _clipped_sum,
    cholesky_solve,
    lapack_cholesky_solve,
    lm_kernel,
    register_model,
)
from app.vlp.solvers.gridless.lm import LMSettings, levenberg_marquardt
from app.vlp.typing import FloatArray

ANCHORS = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0], [2.0, -1.0], [5.0, 1.5]])
TRUTH = np.array([1.3, 2.1, 0.25])  # x, y (metres), bias
LOWER = np.array([0.0, 0.0, -1.0])
UPPER = np.array([4.0, 3.0, 1.0])
START = np.array([3.2, 0.4, 0.0])


def ranges(theta: FloatArray) -> FloatArray:
    return np.asarray(np.hypot(*(theta[:2] - ANCHORS).T) + theta[2])


def measured(seed: int) -> FloatArray:
    return ranges(TRUTH) + 0.01 * np.random.default_rng(seed).standard_normal(len(ANCHORS))


class RangesModel(NamedTuple):
    anchors: FloatArray
    data: FloatArray


def ranges_evaluate(
    model: RangesModel, theta: FloatArray
) -> tuple[float, tuple[FloatArray, FloatArray]]:
    anchors, data = model
    n = anchors.shape[0]
    residual = np.empty(n)
    jacobian = np.empty((n, 3))
    for i in range(n):
        dx, dy = theta[0] - anchors[i, 0], theta[1] - anchors[i, 1]
        distance = np.sqrt(dx * dx + dy * dy)
        residual[i] = data[i] - distance - theta[2]
        jacobian[i, 0], jacobian[i, 1], jacobian[i, 2] = dx / distance, dy / distance, 1.0
    return float(residual @ residual), (residual, jacobian)


def ranges_normal_equations(
    _model: RangesModel, _theta: FloatArray, point: tuple[FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray]:
    residual, jacobian = point
    return jacobian.T @ jacobian, jacobian.T @ residual


# Compiled here without the disk cache (which keeps the solver's models only): the ranges
# model, and the compiled loop's own code.
_njit: Any = numba.njit
register_model(RangesModel, _njit(ranges_evaluate), _njit(ranges_normal_equations))
_lm_loop = _njit(cast(Any, lm_kernel).py_func)


def fit_reference(
    data: FloatArray, settings: LMSettings, upper: FloatArray = UPPER
) -> tuple[FloatArray, float, int, tuple[FloatArray, FloatArray]]:
    """The NumPy loop on the ranges model (the same functions the compiled loop runs)."""
    return levenberg_marquardt(
        lambda theta: ranges_evaluate(RangesModel(ANCHORS, data), theta),
        lambda theta, point: ranges_normal_equations(RangesModel(ANCHORS, data), theta, point),
        START.copy(),
        LOWER,
        upper,
        settings,
    )


def fit_compiled(
    data: FloatArray, settings: LMSettings, upper: FloatArray = UPPER
) -> tuple[FloatArray, float, int, tuple[FloatArray, FloatArray]]:
    theta, cost, used, point = _lm_loop(
        RangesModel(ANCHORS, data),
        START.copy(),
        LOWER,
        upper,
        settings,
    )
    return theta, float(cost), int(used), point


def settings(before_trial: bool, max_iter: int = 50, tol: float = 1e-14) -> LMSettings:
    return LMSettings(max_iter, 1e-2, 10, tol, 1e-10, 2, before_trial)


@pytest.mark.parametrize("before_trial", [True, False])
def test_reaches_the_least_squares_minimum(before_trial: bool) -> None:
    """Inside the bounds, the fit ends at the minimum scipy's trust-region solver finds."""
    data = measured(1)
    want = optimize.least_squares(
        lambda theta: data - ranges(theta), START, xtol=1e-15, ftol=1e-15, gtol=1e-15
    ).x
    theta, cost, used, (residual, _) = fit_reference(data, settings(before_trial))
    np.testing.assert_allclose(theta, want, rtol=0.0, atol=1e-8)
    assert cost == pytest.approx(float(residual @ residual), rel=1e-14)
    assert cost == pytest.approx(float(np.sum((data - ranges(want)) ** 2)), rel=1e-8)
    assert 1 < used < 50


def test_keeps_theta_within_its_bounds() -> None:
    """With the bias bounded below its value, the fit ends on that bound, with a cost below
    the start's and not below the minimum over the box (scipy's bounded trust-region
    solver; a clipped step need not reach it exactly)."""
    data = measured(2)
    upper = np.array([4.0, 3.0, 0.1])
    best = optimize.least_squares(
        lambda theta: data - ranges(theta),
        START,
        bounds=(LOWER, upper),
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    theta, cost, *_ = fit_reference(data, settings(False), upper)
    assert np.all(theta >= LOWER) and np.all(theta <= upper)
    assert theta[2] == 0.1
    assert 2.0 * best.cost * (1.0 - 1e-12) <= cost < float(np.sum((data - ranges(START)) ** 2))
    np.testing.assert_allclose(theta[:2], best.x[:2], rtol=0.0, atol=0.02)


@pytest.mark.parametrize("before_trial", [True, False])
def test_stop_rules(before_trial: bool) -> None:
    """``max_iter`` caps the iterations; a step small enough to end the fit ends it after
    one iteration; a coarse cost tolerance ends it sooner than a fine one."""
    data = measured(3)
    assert fit_reference(data, settings(before_trial, max_iter=3))[2] == 3
    coarse = settings(before_trial)._replace(step_tol=np.inf)
    assert fit_reference(data, coarse)[2] == 1
    fine = fit_reference(data, settings(before_trial))[2]
    assert fit_reference(data, settings(before_trial, tol=1e-2))[2] < fine


@pytest.mark.parametrize("before_trial", [True, False])
@pytest.mark.parametrize("max_iter", [2, 50])
@pytest.mark.parametrize("seed", [4, 5])
def test_kernel_matches_reference(before_trial: bool, max_iter: int, seed: int) -> None:
    """The compiled loop gives the NumPy loop's fit: theta, cost, iterations and point."""
    data = measured(seed)
    chosen = settings(before_trial, max_iter=max_iter, tol=1e-9)
    want = fit_reference(data, chosen)
    got = fit_compiled(data, chosen)
    assert got[2] == want[2]
    np.testing.assert_allclose(got[0], want[0], rtol=1e-10, atol=0.0)
    assert got[1] == pytest.approx(want[1], rel=1e-10)
    for got_part, want_part in zip(got[3], want[3], strict=True):
        np.testing.assert_allclose(got_part, want_part, rtol=0.0, atol=1e-10)


@pytest.mark.parametrize("solve", [cholesky_solve, lapack_cholesky_solve])
def test_cholesky_solves_as_lapack_posv(solve: Any) -> None:
    """The compiled loop's solves: LAPACK's ``posv`` (the reference's) numbers for a
    positive definite matrix, and a failure where ``posv`` fails (indefinite, singular)."""
    rng = np.random.default_rng(43)
    square = rng.standard_normal((7, 7))
    rhs = rng.standard_normal(7)
    definite = square @ square.T + 0.1 * np.eye(7)
    step, solved = solve(definite, rhs)
    _, want, info = lapack.dposv(definite, rhs)
    assert solved and info == 0
    np.testing.assert_allclose(step, want, rtol=1e-10, atol=0.0)
    for matrix in (square + square.T - 10.0 * np.eye(7), np.zeros((7, 7))):
        assert lapack.dposv(matrix, rhs)[2] != 0
        assert not solve(matrix, rhs)[1]


@numba.njit(cache=False)
def _ufunc_clip(
    theta: FloatArray, step: FloatArray, lower: FloatArray, upper: FloatArray
) -> FloatArray:
    return np.minimum(np.maximum(theta + step, lower), upper)


def test_a_trial_is_clipped_as_the_ufuncs_clip_it() -> None:
    """The compiled loop's trial, ``theta + step`` within the bounds in one pass: to the bit
    what ``np.minimum(np.maximum(theta + step, lower), upper)`` gives in compiled code (NaN
    kept, infinite bounds, and a signed zero where compiled ``np.maximum`` keeps it; NumPy's
    own ufuncs differ from both only in a zero's sign)."""
    rng = np.random.default_rng(44)
    special = [[-0.0, -0.0, 0.0, 0.0], [0.0, -0.0, 0.0, np.inf], [-0.0, -0.0, -1.0, -0.0]]
    special += [[1.0, np.nan, 0.0, 1.0], [3.0, np.inf, 0.0, 2.0], [0.0, -1.0, -np.inf, np.inf]]
    theta, step, lower, upper = np.concatenate(
        (
            np.stack(
                (
                    rng.uniform(-2.0, 2.0, 20),
                    rng.uniform(-2.0, 2.0, 20),
                    np.full(20, -1.0),
                    np.full(20, 1.0),
                )
            ),
            np.array(special).T,
        ),
        axis=1,
    )
    want = _ufunc_clip(theta, step, lower, upper)
    got = _clipped_sum(theta, step, lower, upper)
    np.testing.assert_array_equal(got, want)  # NaN where NaN
    assert np.array_equal(np.signbit(got), np.signbit(want))
    np.testing.assert_array_equal(got, np.clip(theta + step, lower, upper))
    assert np.count_nonzero(got == lower) > 0 and np.count_nonzero(got == upper) > 0
