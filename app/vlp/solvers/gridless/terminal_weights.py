"""A terminal's amplitude weights: a fit whitened anew, the survey's measured scatter, and the
likelihood that tells a refit from a walk-off (:mod:`.terminal_solve`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ...layout import AmplitudeError
from ...typing import FloatArray
from ...uncertainty import Misfit, MisfitDesign, fit_misfit
from .terminals import TerminalFit

# Standard deviations of the chi-square by which a request's residuals may exceed what the
# survey's measured scatter predicts and still be taken for the survey receiver's kind.
_SCATTER_SIGNIFICANCE = 3.0
# Residual degrees of freedom a terminal's fit needs before its own residuals can estimate
# its variances: on fewer, the F(2, nu) of its radius has no finite mean.
_OWN_VARIANCE_MIN_DOF = 3


def rewhitened(fit: TerminalFit, weight: float | FloatArray) -> TerminalFit:
    """``fit`` at its own optimum with its data rows whitened by ``weight`` instead of its
    own (its residual, Jacobian, normal matrix and cost; the priors' rows unchanged)."""
    ratio = np.broadcast_to(np.asarray(weight / np.asarray(fit.data_weight)), fit.residual.shape)
    residual = fit.residual * ratio
    jacobian = fit.jacobian * ratio[:, None]
    normal = fit.normal - fit.jacobian.T @ fit.jacobian + jacobian.T @ jacobian
    cost = fit.cost - float(fit.residual @ fit.residual) + float(residual @ residual)
    return replace(
        fit, residual=residual, jacobian=jacobian, normal=normal, cost=cost, data_weight=weight
    )


def terminal_nll(fit: TerminalFit, variances: FloatArray, tail_dof: float | None) -> float:
    """Minus the log-likelihood of a terminal's amplitudes at ``fit`` (up to a constant),
    each of variance (or, with ``tail_dof``, squared Student-t scale) ``variances`` (M,), plus
    its priors' (half the prior rows' squares of its cost)."""
    residual = fit.residual / fit.data_weight  # unwhitened
    ratio = residual**2 / variances
    if tail_dof is None:
        data = 0.5 * float(np.sum(np.log(variances) + ratio))
    else:
        data = float(
            np.sum(0.5 * np.log(variances) + 0.5 * (tail_dof + 1.0) * np.log1p(ratio / tail_dof))
        )
    return data + 0.5 * (fit.cost - float(fit.residual @ fit.residual))


def scatter_explains(fits: list[TerminalFit], n_leds: int, tail_dof: float | None) -> bool:
    """Whether the survey's measured scatter explains the residuals of ``fits`` (weighted
    by it, each of ``n_leds`` amplitudes): their whitened sum of squares within
    ``_SCATTER_SIGNIFICANCE`` standard deviations of its mean on their residual degrees of
    freedom. Each square has mean 1 and variance 2 (chi-square), or, weighted as a Student-t
    of ``tail_dof`` degrees of freedom weighs it (``(nu + 1) u^2 / (nu + u^2)``, a scaled
    Beta(1/2, nu/2)), mean 1 and variance ``2 nu / (nu + 3)``. A terminal whose tilt, gain or
    height is unlike the survey receiver's leaves more."""
    chi2 = sum(float(fit.residual @ fit.residual) for fit in fits)
    total = float(sum(max(n_leds - fit.n_params, 1) for fit in fits))
    return chi2 <= total + _SCATTER_SIGNIFICANCE * math.sqrt(
        weighted_square_variance(tail_dof) * total
    )


def own_variances_estimable(fits: list[TerminalFit], n_leds: int) -> bool:
    """Whether the residuals of ``fits`` (each of ``n_leds`` amplitudes) can estimate their
    own variances in place of the survey's scatter: some fit leaves at least
    ``_OWN_VARIANCE_MIN_DOF`` residual degrees of freedom. One terminal of a room with five
    LEDs leaves 2 or fewer: its residuals can neither tell its kind from the survey
    receiver's nor say how much wider its radius should be (such an estimate widened
    radii tenfold on a measured five-LED room)."""
    return any(n_leds - fit.n_params >= _OWN_VARIANCE_MIN_DOF for fit in fits)


def weighted_square_variance(tail_dof: float | None) -> float:
    """The variance of one whitened residual's square, ``u^2`` for a Gaussian ``u`` (2), or
    ``(nu + 1) u^2 / (nu + u^2)`` for a Student-t ``u`` of ``nu = tail_dof`` degrees of freedom
    weighted as its fit weighs it: ``(nu + 1)`` times a Beta(1/2, nu/2), variance
    ``2 nu / (nu + 3)`` (its mean is 1 either way)."""
    return 2.0 if tail_dof is None else 2.0 * tail_dof / (tail_dof + 3.0)


def measured_variances(measured: AmplitudeError, scale: float, fit: TerminalFit) -> FloatArray:
    """Each of a terminal's amplitudes' variance (M,), in the solver's units (amplitudes
    over ``scale``), from the room's measured scatter at the fit's modelled amplitudes:
    ``noise_sd^2 + (relative_sd f_i)^2``."""
    modelled = fit.jacobian[:, -1] / fit.data_weight  # the log gain's column, unwhitened
    return np.asarray(
        (measured.noise_sd / scale) ** 2 + (measured.relative_sd * modelled) ** 2,
        dtype=np.float64,
    )


def tail_weighted_variances(measured: AmplitudeError, scale: float, fit: TerminalFit) -> FloatArray:
    """Each of a terminal's amplitudes' variance (M,) for the next reweighting of a Student-t
    scatter (``measured.tail_dof``): its squared scale (:func:`measured_variances`) over the
    t's weight ``(nu + 1) / (nu + u^2)``, ``u`` its residual at ``fit`` over that scale."""
    squared_scales = measured_variances(measured, scale, fit)
    nu = measured.tail_dof
    if nu is None:
        return squared_scales
    residuals = fit.residual / fit.data_weight  # unwhitened
    u2 = residuals**2 / squared_scales
    return np.asarray(squared_scales * (nu + u2) / (nu + 1.0), dtype=np.float64)


def measured_misfit(
    measured: AmplitudeError, designs: list[MisfitDesign], residuals: list[FloatArray]
) -> Misfit:
    """The variances of fits weighted by the room's measured scatter: their whitened noise
    is 1, resting on the survey's degrees of freedom; the terminals' own tilts and heights
    (not the survey receiver's) are still fitted to the request's residuals."""
    misfit = fit_misfit(designs, residuals, noise=1.0)
    return replace(misfit, dofs=np.r_[measured.dof, misfit.dofs[1:]])
