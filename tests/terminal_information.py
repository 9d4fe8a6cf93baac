"""The covariance a terminal's fit should report, computed apart from the solver: the inverse
of the information of (x, y, log gain) by central differences of the simulator's channel."""

from __future__ import annotations

import math

import numpy as np

from app.vlp.layout import Layout
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers.gridless import GridlessOptions


def position_covariance(
    layout: Layout, position: np.ndarray, gain: float, noise_sd: float
) -> np.ndarray:
    """Shape (2, 2): the position block of the inverse information of (x, y, log gain) at
    ``position`` (2,) and ``gain``, for amplitudes with noise ``noise_sd``, the log gain under
    the default solver's prior."""

    def model(theta: np.ndarray) -> np.ndarray:
        return np.asarray(math.exp(theta[2]) * true_amplitudes(layout, theta[None, :2])[0])

    theta = np.r_[position, math.log(gain)]
    step = 1e-6
    jacobian = np.column_stack(
        [(model(theta + step * e) - model(theta - step * e)) / (2 * step) for e in np.eye(3)]
    )
    gain_sd = GridlessOptions().log_gain_sd
    assert gain_sd is not None
    information = jacobian.T @ jacobian / noise_sd**2 + np.diag([0.0, 0.0, 1.0 / gain_sd**2])
    return np.asarray(np.linalg.inv(information)[:2, :2])
