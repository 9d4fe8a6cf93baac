"""Levenberg-Marquardt: the one loop every fit of the default solver runs (NumPy reference
here, its compiled twin :func:`.gridless._compiled.lm.lm_kernel`), its settings and all its
constants. Private: callers validate.

A fit hands the loop two functions of its model (docs/explanation/solver.md,
"Levenberg-Marquardt"):

- ``evaluate(theta) -> (cost, point)``: the cost at ``theta`` and whatever the model keeps of
  that evaluation (``point``), enough to accept or reject a trial step;
- ``normal_equations(theta, point) -> (J^T J, J^T r)``: asked once per iteration, at the
  accepted point (a model may delay its Jacobian to here: a rejected trial never needs it).

The aggregated fit (``gridless.model.fit_objective``) keeps each trial's rotated gains and
builds ``J^T J`` from them at accepted points (its NumPy reference takes ``J^T J`` with every
trial, one product giving it with the cost); the terminal fit (``gridless.terminals``) keeps its
residual and Jacobian, which it reports; the joint room-tolerance fit
(``gridless.tolerances``) keeps its residual and computes its Jacobian only at accepted
points. The compiled kernels read the constants below as compile-time constants.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import numpy as np
from scipy.linalg import lapack

from ...typing import FloatArray

__all__ = [
    "DAMPING_DOWN",
    "DAMPING_SINGULAR",
    "DAMPING_UP",
    "DIAGONAL_FLOOR",
    "EIG_FLOOR",
    "MAX_REJECTIONS",
    "MIN_DAMPING",
    "PROJECTED_MAX_REJECTIONS",
    "SIGMA2_FLOOR",
    "STEP_TOL_M",
    "TERMINAL_COST_TOL",
    "TERMINAL_INITIAL_DAMPING",
    "TERMINAL_STEP_TOL_M",
    "TOLERANCE_INITIAL_DAMPING",
    "LMSettings",
    "least_squares_normal_equations",
    "least_squares_point",
    "levenberg_marquardt",
]

# Damping increases tried per iteration before the point is taken as a local minimum: the
# aggregated fit (positions, weights, heights, gains, noise), and the terminal and joint
# room-tolerance fits.
MAX_REJECTIONS = 12
PROJECTED_MAX_REJECTIONS = 10
# Marquardt damping factors after a rejected / accepted step (the start is the caller's).
# Nielsen's adaptive update needs fewer evaluations but lands in worse local minima on
# irregular rooms (measured in docs/decisions/gridless-defaults.md).
DAMPING_UP = 4.0
DAMPING_DOWN = 5.0
# Damping factor when the damped normal equations cannot be solved (not positive definite).
DAMPING_SINGULAR = 10.0
# The damping never falls below this.
MIN_DAMPING = 1e-9
# Floor on the normal matrix's diagonal in the Marquardt scaling (a parameter no residual
# depends on still gets a damped, finite step).
DIAGONAL_FLOOR = 1e-30
# Relative floor on whitening eigenvalues (guards a noiseless fit against infinite weights),
# and the smallest noise variance (normalised units) assumed when whitening.
EIG_FLOOR = 1e-9
SIGMA2_FLOOR = 1e-12
# Smallest noise variance assumed relative to the mean received power (1e-4: an SNR of
# 40 dB), in the whitening (compiled and reference alike) and in a terminal's weights.
SIGMA2_REL_FLOOR = 1e-4
# The aggregated LM stops when no target moves by more than this (metres).
STEP_TOL_M = 1e-5
# A terminal's own fit: its starting damping, and it stops at this relative decrease of the
# cost or when its position moves by less than this (metres).
TERMINAL_INITIAL_DAMPING = 1e-3
TERMINAL_COST_TOL = 1e-10
TERMINAL_STEP_TOL_M = 1e-6
# The joint room-tolerance fit's starting damping.
TOLERANCE_INITIAL_DAMPING = 1e-2


class LMSettings(NamedTuple):
    """One fit's iterations, damping and stop rule (a plain tuple for the compiled loop).

    Besides ``max_iter`` iterations, a fit ends at a point that no damping of
    ``max_rejections`` improves, and after a step that is small: one that moves none of the
    first ``n_positions`` entries of theta (the positions, metres) by ``step_tol`` or more,
    or an accepted one that lowers the cost by less than ``cost_tol`` of it.

    With ``before_trial`` (the aggregated fit), a step is tested before it is tried, both for
    its size and for the decrease its linearised model predicts (below ``cost_tol`` of the
    cost is small): it is still tried, and then ends the fit, accepted or not. Without it,
    only an accepted step is tested, for its size and its actual decrease.
    """

    max_iter: int
    damping: float  # the starting damping, relative to the normal matrix's diagonal
    max_rejections: int
    cost_tol: float
    step_tol: float  # 0: no such rule
    n_positions: int
    before_trial: bool


_Point = TypeVar("_Point")
# A least-squares model's point: its residual (L,) and Jacobian (L, P).
ResidualPoint = tuple[FloatArray, FloatArray]


def least_squares_point(residual: FloatArray, jacobian: FloatArray) -> tuple[float, ResidualPoint]:
    """``evaluate``'s answer for a model that gives its residual and Jacobian: the cost
    ``r^T r`` and the point. A wild trial may overflow: its cost is then inf (or nan), and
    :func:`levenberg_marquardt` rejects it."""
    with np.errstate(over="ignore", invalid="ignore"):
        cost = float(residual @ residual)
    return cost, (residual, jacobian)


def least_squares_normal_equations(
    _theta: FloatArray, point: ResidualPoint
) -> tuple[FloatArray, FloatArray]:
    """``normal_equations`` of such a model: ``J^T J`` and ``J^T r`` at its point."""
    residual, jacobian = point
    return jacobian.T @ jacobian, jacobian.T @ residual


def levenberg_marquardt(
    evaluate: Callable[[FloatArray], tuple[float, _Point]],
    normal_equations: Callable[[FloatArray, _Point], tuple[FloatArray, FloatArray]],
    theta: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float, int, _Point]:
    """Minimise the cost ``||r(theta)||^2`` with ``theta`` kept within ``[lower, upper]``
    (each trial is clipped to them).

    Parameters
    ----------
    evaluate : callable
        ``theta -> (cost, point)``.
    normal_equations : callable
        ``(theta, point) -> (J^T J, J^T r)``, with ``J = -dr/dtheta`` (the model's
        derivative when ``r`` is data minus model), ``point`` the one ``evaluate`` gave.
    theta : ndarray of shape (P,)
        Start, within the bounds.
    lower, upper : ndarrays of shape (P,)
    settings : LMSettings

    Returns
    -------
    theta, cost, iterations, point
        At the last accepted point, and the iterations begun.
    """
    cost, point = evaluate(theta)
    damping = settings.damping
    used = 0
    converged = False
    while used < settings.max_iter and not converged:
        used += 1
        normal, gradient = normal_equations(theta, point)
        scaling = np.diag(np.maximum(normal.diagonal(), DIAGONAL_FLOOR))
        for _ in range(settings.max_rejections):
            _, step, info = lapack.dposv(normal + damping * scaling, gradient)
            if info != 0:
                damping *= DAMPING_SINGULAR
                continue
            small = _small_step(step, settings)
            if settings.before_trial:
                predicted = float(step @ (2.0 * gradient - normal @ step))
                converged = small or predicted < settings.cost_tol * cost
            trial = np.clip(theta + step, lower, upper)
            # A wild trial may overflow: its cost is then inf (or nan) and it is rejected.
            trial_cost, trial_point = evaluate(trial)
            if trial_cost < cost:
                converged = converged or small or (cost - trial_cost) < settings.cost_tol * cost
                theta, cost, point = trial, trial_cost, trial_point
                damping = max(damping / DAMPING_DOWN, MIN_DAMPING)
                break
            if converged:
                break
            damping *= DAMPING_UP
        else:
            converged = True  # no decrease found along any damping: a local minimum
    return theta, cost, used, point


def _small_step(step: FloatArray, settings: LMSettings) -> bool:
    """Whether ``step`` moves no position by ``settings.step_tol`` or more."""
    n = settings.n_positions
    largest = float(np.abs(step[:n]).max()) if n else 0.0
    return largest < settings.step_tol


def whitening_weight(amplitudes: FloatArray, sigma2: float | FloatArray) -> float | FloatArray:
    """The whitening weight ``1 / sqrt(sigma2)`` of a terminal's amplitudes (M,) of noise
    variance ``sigma2`` (scalar or (M,)), the variance floored at ``SIGMA2_REL_FLOOR`` of their
    mean square."""
    floor = max(SIGMA2_REL_FLOOR * float(amplitudes @ amplitudes) / amplitudes.shape[0], 1e-300)
    if isinstance(sigma2, np.ndarray):
        return np.asarray(1.0 / np.sqrt(np.maximum(sigma2, floor)), dtype=np.float64)
    return 1.0 / math.sqrt(max(float(sigma2), floor))
