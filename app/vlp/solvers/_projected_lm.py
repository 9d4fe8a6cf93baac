"""A small projected Levenberg-Marquardt in NumPy for fits whose residual and Jacobian come
from one callback (the terminal fit, the room-tolerance fit). Private: callers validate.

The nominal aggregated fit has its own compiled loop (``_fit_compiled.lm_kernel``), and so
does the terminal fit (``_terminal_compiled.terminal_lm_kernel``, this loop its reference).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..typing import FloatArray

__all__ = ["projected_levenberg_marquardt"]

# Damping increases tried per iteration before the point is taken as a local minimum.
_MAX_REJECTIONS = 10

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
        for _ in range(_MAX_REJECTIONS):
            scaled = normal + damping * np.diag(np.maximum(normal.diagonal(), 1e-30))
            try:
                step = np.asarray(np.linalg.solve(scaled, gradient), dtype=np.float64)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = np.clip(theta + step, lower, upper)
            trial_residual, trial_jacobian = evaluate(trial)
            # A wild trial may overflow: its cost is then inf (or nan) and it is rejected.
            with np.errstate(over="ignore", invalid="ignore"):
                trial_cost = float(trial_residual @ trial_residual)
            if trial_cost < cost:
                finished = stop(step, cost, trial_cost)
                theta, residual, jacobian, cost = trial, trial_residual, trial_jacobian, trial_cost
                damping = max(damping / 5.0, 1e-9)
                improved = True
                break
            damping *= 4.0
        if not improved or finished:
            break
    return theta, residual, jacobian, cost
