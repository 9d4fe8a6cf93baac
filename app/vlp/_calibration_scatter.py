"""How a survey's amplitudes scatter around the calibrated model: the room's ``AmplitudeError``.

Each detected amplitude ``a`` of model value ``f`` is ``f`` plus an error of scale
``sqrt(s^2 + (b f)^2)``: the receiver's noise, and what the model misses in proportion to the
signal (beams that are not Lambertian, reflections). Measured surveys leave a few errors far
beyond that scale (an LED's edge of beam, a reflection the model lacks): their errors follow a
Student-t distribution of few degrees of freedom rather than a Gaussian. When the survey shows
it (the t-distribution's likelihood beats the Gaussian's by more than chance), the room's
scatter is that t-distribution; terminals are then fitted with it (each amplitude weighted by
how far its own residual lies in the tails, :mod:`app.vlp.solvers.gridless.terminal_solve`).
See docs/decisions/measured-radii.md.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize, special

from .layout import AmplitudeError
from .survey import Survey
from .typing import FloatArray

__all__ = ["survey_scatter"]

# Rounds of reweighting the moment fit of the Gaussian scatter.
_MOMENT_REWEIGHTS = 6
# The t-distribution's degrees of freedom are fitted within these bounds; beyond the upper one
# it is a Gaussian for any number of amplitudes a terminal sends.
_TAIL_DOF_BOUNDS = (1.0, 100.0)
# It replaces the Gaussian only when its log-likelihood is higher by more than this (half the
# 99.9 % quantile of chi-square with one degree of freedom: one extra parameter).
_TAIL_LOG_LIKELIHOOD_GAIN = 0.5 * 10.83


def survey_scatter(survey: Survey, modelled: FloatArray, n_params: int) -> AmplitudeError | None:
    """The survey's scatter around the calibrated model, over the rows the model sees
    (detected, ``f > 0``).

    The Gaussian ``E[(a - f)^2] = s^2 + (b f)^2`` is fitted to the squared residuals
    (non-negative least squares, reweighted by each square's expected scatter, ``2 E^2``),
    then a Student-t of scale ``sqrt(s^2 + (b f)^2)`` and ``nu`` degrees of freedom by maximum
    likelihood; the t is kept when it explains the residuals significantly better. The fit of
    the LEDs' ``n_params`` parameters absorbed part of the residuals: ``s^2, b^2`` are scaled by
    ``n / (n - n_params)``, the ``n - n_params`` degrees of freedom they rest on. None when
    none is left.

    Parameters
    ----------
    survey : Survey
        S rows of measured amplitudes.
    modelled : ndarray of shape (S,)
        The calibrated model's amplitude of each row.
    n_params : int
        The calibration's fitted parameters.
    """
    used = survey.detected & (modelled > 0.0)
    n_used = int(np.count_nonzero(used))
    dof = n_used - n_params
    if dof < 1:
        return None
    model = modelled[used]
    residuals = survey.amplitudes[used] - model
    noise_var, relative_var = _gaussian_moments(residuals, model)
    gaussian_nll = _gaussian_nll(residuals, model, (noise_var, relative_var))
    tail = _student_t(residuals, model, (noise_var, relative_var))
    tail_dof = None
    if tail is not None and gaussian_nll - tail[2] > _TAIL_LOG_LIKELIHOOD_GAIN:
        noise_var, relative_var, _, tail_dof = tail
    inflation = n_used / dof
    return AmplitudeError(
        math.sqrt(noise_var * inflation),
        math.sqrt(relative_var * inflation),
        float(dof),
        tail_dof=tail_dof,
    )


def _gaussian_moments(residuals: FloatArray, model: FloatArray) -> tuple[float, float]:
    """``(s^2, b^2)`` of ``E[r^2] = s^2 + b^2 f^2`` (reweighted non-negative least squares)."""
    squares = residuals**2
    design = np.column_stack((np.ones(model.size), model**2))
    weights = np.ones(model.size)
    solution = np.zeros(2)
    for _ in range(_MOMENT_REWEIGHTS):
        solution, _ = optimize.nnls(design * weights[:, None], squares * weights)
        expected = design @ solution
        weights = 1.0 / np.maximum(expected, 1e-3 * max(float(np.mean(expected)), 1e-300))
    return float(solution[0]), float(solution[1])


def _t_nll(variances: FloatArray, nu: float, residuals: FloatArray, model: FloatArray) -> float:
    """Negative log-likelihood of ``residuals`` under a t (``nu``; inf: Gaussian) of squared
    scale ``variances[0] + variances[1] f^2``."""
    scale2 = np.maximum(variances[0] + variances[1] * model**2, 1e-300)
    u2 = residuals**2 / scale2
    if math.isinf(nu):
        return float(0.5 * np.sum(np.log(2.0 * math.pi * scale2) + u2))
    constant = special.gammaln((nu + 1.0) / 2.0) - special.gammaln(nu / 2.0)
    return float(
        np.sum(0.5 * np.log(nu * math.pi * scale2) + (nu + 1.0) / 2.0 * np.log1p(u2 / nu))
        - residuals.size * constant
    )


def _log_scales(residuals: FloatArray, moments: tuple[float, float]) -> FloatArray:
    """``log(s^2), log(b^2)`` of the moments, kept off zero (a search starts from them)."""
    floor = 1e-12 * max(float(np.mean(residuals**2)), 1e-300)
    return np.asarray(np.log(np.maximum(np.array(moments), [floor, 1e-12])), dtype=np.float64)


def _gaussian_nll(residuals: FloatArray, model: FloatArray, start: tuple[float, float]) -> float:
    """The Gaussian's lowest negative log-likelihood (its scales by maximum likelihood,
    started from the moments ``start``): what the t must beat."""
    begin = _log_scales(residuals, start)
    result = optimize.minimize(
        lambda p: _t_nll(np.exp(p), math.inf, residuals, model),
        begin,
        method="Nelder-Mead",
        options={"maxiter": 2000, "xatol": 1e-6},
    )
    return float(min(result.fun, _t_nll(np.exp(begin), math.inf, residuals, model)))


def _student_t(
    residuals: FloatArray, model: FloatArray, gaussian: tuple[float, float]
) -> tuple[float, float, float, float] | None:
    """The t's ``(s^2, b^2, nll, nu)`` of highest likelihood, started from the Gaussian's
    scales; None when the search fails."""
    start = np.r_[_log_scales(residuals, gaussian), math.log(4.0)]

    def objective(p: FloatArray) -> float:
        nu = float(np.clip(math.exp(p[2]), *_TAIL_DOF_BOUNDS))
        return _t_nll(np.exp(p[:2]), nu, residuals, model)

    result = optimize.minimize(
        objective, start, method="Nelder-Mead", options={"maxiter": 3000, "xatol": 1e-6}
    )
    if not np.isfinite(result.fun):
        return None
    nu = float(np.clip(math.exp(result.x[2]), *_TAIL_DOF_BOUNDS))
    if nu >= _TAIL_DOF_BOUNDS[1]:
        return None
    noise_var, relative_var = (float(v) for v in np.exp(result.x[:2]))
    return noise_var, relative_var, float(result.fun), nu
