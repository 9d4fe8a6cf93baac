"""Levenberg-Marquardt: the constants every fit of the default solver uses, and a small
projected loop in NumPy for fits whose residual and Jacobian come from one callback (the
terminal fit, the room-tolerance fit). Private: callers validate.

Every LM loop -- the aggregated fit's NumPy reference (``gridless.model.levenberg_marquardt``)
and its compiled twin (``gridless._compiled.fit.lm_kernel``), the terminal fit's
(``gridless._compiled.terminal.terminal_lm_kernel``, this loop its reference) and the joint
room-tolerance fit's (``gridless._compiled.tolerance.joint_lm_kernel``, this loop its reference) --
imports its damping schedule and floors from here: one source for each constant. The
compiled kernels read them as compile-time constants.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

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
    "projected_levenberg_marquardt",
]

# Damping increases tried per iteration before the point is taken as a local minimum: the
# aggregated fit (positions, weights, heights, gains, noise) and the projected loops below.
MAX_REJECTIONS = 12
PROJECTED_MAX_REJECTIONS = 10
# Marquardt damping factors after a rejected / accepted step (the start is the caller's).
# Nielsen's adaptive update needs fewer evaluations but lands in worse local minima on
# irregular rooms (measured in docs/decisions/gridless-defaults.md).
DAMPING_UP = 4.0
DAMPING_DOWN = 5.0
# Damping factor when the damped normal equations cannot be solved (singular).
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
# The aggregated LM stops when no target moves by more than this (metres).
STEP_TOL_M = 1e-5
# A terminal's own fit: its starting damping, and it stops at this relative decrease of the
# cost or when its position moves by less than this (metres).
TERMINAL_INITIAL_DAMPING = 1e-3
TERMINAL_COST_TOL = 1e-10
TERMINAL_STEP_TOL_M = 1e-6
# The joint room-tolerance fit's starting damping.
TOLERANCE_INITIAL_DAMPING = 1e-2

Evaluate = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
Stop = Callable[[FloatArray, float, float], bool]


def projected_levenberg_marquardt(
    evaluate: Evaluate,
    theta: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    *,
    max_iter: int,
    damping: float,
    stop: Stop,
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Minimise ``||r(theta)||^2`` with ``theta`` kept within ``[lower, upper]``.

    Parameters
    ----------
    evaluate : callable
        ``theta -> (r, J)``, shapes (L,) and (L, P), with ``J = -dr/dtheta`` (the model's
        derivative when ``r`` is data minus model).
    theta : ndarray of shape (P,)
        Start.
    lower, upper : ndarrays of shape (P,)
    max_iter : int
    damping : float
        Initial Marquardt damping (relative to the normal matrix's diagonal).
    stop : callable
        ``(step, cost, trial_cost) -> bool``, asked after an accepted step: True ends the fit.

    Returns
    -------
    theta, residual, jacobian, cost
        At the last accepted point.
    """
    residual, jacobian = evaluate(theta)
    cost = float(residual @ residual)
    for _ in range(max_iter):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
        improved = finished = False
        for _ in range(PROJECTED_MAX_REJECTIONS):
            scaled = normal + damping * np.diag(np.maximum(normal.diagonal(), DIAGONAL_FLOOR))
            try:
                step = np.asarray(np.linalg.solve(scaled, gradient), dtype=np.float64)
            except np.linalg.LinAlgError:
                damping *= DAMPING_SINGULAR
                continue
            trial = np.clip(theta + step, lower, upper)
            trial_residual, trial_jacobian = evaluate(trial)
            # A wild trial may overflow: its cost is then inf (or nan) and it is rejected.
            with np.errstate(over="ignore", invalid="ignore"):
                trial_cost = float(trial_residual @ trial_residual)
            if trial_cost < cost:
                finished = stop(step, cost, trial_cost)
                theta, residual, jacobian, cost = trial, trial_residual, trial_jacobian, trial_cost
                damping = max(damping / DAMPING_DOWN, MIN_DAMPING)
                improved = True
                break
            damping *= DAMPING_UP
        if not improved or finished:
            break
    return theta, residual, jacobian, cost
