"""How much to trust an answer: the goodness of a fit and the covariance that carries its
model errors (the radii drawn from it: :mod:`app.vlp.radii`).

A fit's covariance starts from its Fisher information (the Gauss-Newton normal matrix of the
whitened residuals and priors at the optimum), which counts the noise only. A real room
differs from its model (LEDs off their data sheet, tilted or higher receivers, reflections),
and that error scales with the signal, lies partly along what the fit can absorb (a tilt
looks like a shift) and does not show in a reduced chi-square: the nuisance parameters and
the fitted noise level soak it up. So the model errors the fit does not fit are written as
columns ``F_c`` (the model's derivative along each), their variances are estimated from the
residuals' squares net of what the fit absorbed (:class:`MisfitDesign`, :func:`fit_misfit`),
the covariance is the sandwich that carries all of each error, and it is widened for the few
degrees of freedom behind those variances (:func:`predictive_covariances`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import optimize, special

from .typing import FloatArray, IntArray

__all__ = [
    "FITS_TO_NOISE",
    "NOISE_ONLY_P",
    "POOR_FIT_CHI2",
    "SCALE_MISMATCH_FACTOR",
    "FitQuality",
    "Misfit",
    "MisfitDesign",
    "Quality",
    "assess_fit",
    "f2_widening",
    "fit_misfit",
    "misfit_design_reference",
    "own_excess_widening",
    "predictive_covariances",
]

Quality = Literal["ok", "poor", "scale_mismatch"]

# A reduced chi-square above this says the model does not explain the measurement (the
# room's reflections, gains or geometry differ from its layout): answered, but flagged.
POOR_FIT_CHI2 = 4.0
# Below that, a chi-square that noise alone would exceed less often than this is still
# answered "ok" (the radii carry the model errors) but its detail says the room differs a
# little from its layout, not that the model explains the measurement to its noise.
NOISE_ONLY_P = 1e-3
# The detail of a fit whose residuals are what the noise alone would leave.
FITS_TO_NOISE = "the model explains the measurement to its noise"
# A common amplitude scale outside [1/f, f] says the measurement is not in the fingerprint's
# units (or the pilots / receiver gains changed): answered, but flagged.
SCALE_MISMATCH_FACTOR = 1.5
# Rounds of reweighting in :func:`fit_misfit` (the weights settle within a few).
_MISFIT_REWEIGHTS = 4


@dataclass(frozen=True)
class FitQuality:
    """Goodness of one fit.

    Attributes
    ----------
    chi2_per_dof : float
        Whitened residual sum of squares over its degrees of freedom (about 1 when the
        model explains the data down to the noise).
    scale : float
        Fitted common amplitude scale of the measurement relative to the fingerprint
        (1 = exactly as modelled).
    quality : {"ok", "poor", "scale_mismatch"}
    detail : str
        One sentence for a person.
    dof : int
        Degrees of freedom behind ``chi2_per_dof``.
    """

    chi2_per_dof: float
    scale: float
    quality: Quality
    detail: str
    dof: int = 1


def assess_fit(chi2: float, dof: int, scale: float) -> FitQuality:
    """Classify a fit by its reduced chi-square and its common amplitude scale.

    Parameters
    ----------
    chi2 : float
        Whitened residual sum of squares.
    dof : int
        Its degrees of freedom (observations minus fitted parameters); at least 1 is used.
    scale : float
        Fitted common amplitude scale, positive.

    Examples
    --------
    >>> assess_fit(95.0, 100, 1.02).quality
    'ok'
    >>> assess_fit(95.0, 100, 3.0).quality
    'scale_mismatch'
    """
    dof = max(int(dof), 1)
    reduced = float(chi2) / dof
    if not (1.0 / SCALE_MISMATCH_FACTOR <= scale <= SCALE_MISMATCH_FACTOR):
        detail = (
            f"the measurement is {scale:.3g}x the fingerprint's amplitude scale: check the "
            "units, the pilot amplitudes and the receivers' gain (or calibrate the room)"
        )
        return FitQuality(reduced, scale, "scale_mismatch", detail, dof)
    if reduced > POOR_FIT_CHI2:
        detail = (
            f"the model leaves {reduced:.3g}x the expected residual: the room differs from its "
            "layout (reflections, receivers' gain, height or tilt, LEDs); calibrate the room"
        )
        return FitQuality(reduced, scale, "poor", detail, dof)
    if float(chi2) > float(special.chdtri(dof, NOISE_ONLY_P)):
        detail = (
            f"the model leaves {reduced:.3g}x the expected residual, more than the noise "
            "would: the room differs a little from its layout (reflections, receivers' gain, "
            "height or tilt, LEDs); the radii allow for it"
        )
        return FitQuality(reduced, scale, "ok", detail, dof)
    return FitQuality(reduced, scale, "ok", FITS_TO_NOISE, dof)


@dataclass(frozen=True)
class MisfitDesign:
    """What one whitened least-squares fit needs to weigh model errors against its noise.

    The fit's whitened data ``y = f(theta) + e`` (L values, P parameters, Gaussian priors as
    extra pseudo-residuals) has the error ``e = n + sum_c F_c d_c``: noise ``n ~ N(0, a I)``
    and C kinds of model error ``d_c ~ N(0, b_c I)`` along the columns of ``F_c`` (for
    instance each LED's amplitude off by a relative ``d``: ``F`` holds the signal's
    derivative with respect to it). At the optimum the residual is ``r = Q e`` with
    ``Q = I - J A J^T``, ``A`` the inverse normal matrix, so
    ``E[r_i^2] = a (Q Q^T)_ii + sum_c b_c (Q F_c F_c^T Q^T)_ii``: the part of a model error
    that the fitted parameters absorbed does not show in the residual (it is not counted as
    seen), while the covariance carries all of it (:meth:`covariance`).

    Attributes
    ----------
    inverse : ndarray of shape (P, P)
        ``A``, the inverse (pseudo-inverse) of the fit's normal matrix, priors included.
    data_normal : ndarray of shape (P, P)
        ``J^T J`` of the data alone.
    prior_normal : ndarray of shape (P, P)
        The priors' information (the normal matrix minus ``J^T J``).
    error_normals : ndarray of shape (C, P, P)
        ``(J^T F_c)(J^T F_c)^T``: each model error's information seen by the parameters.
    noise_leverage : ndarray of shape (L,)
        ``(Q Q^T)_ii``: each residual's expected square per unit of noise variance.
    error_leverages : ndarray of shape (L, C)
        ``(Q F_c F_c^T Q^T)_ii``: each residual's expected square per unit of ``b_c``.
    error_spread : ndarray of shape (C,)
        ``tr((Q F_c F_c^T Q^T)^2)``: with ``tr(Q F_c F_c^T Q^T)`` (the column sums of
        ``error_leverages``), the degrees of freedom the residuals hold about ``b_c``.
    """

    inverse: FloatArray
    data_normal: FloatArray
    prior_normal: FloatArray
    error_normals: FloatArray
    noise_leverage: FloatArray
    error_leverages: FloatArray
    error_spread: FloatArray

    def covariance(self, noise: float, model_errors: FloatArray) -> FloatArray:
        """Sandwich covariance of the parameters, shape (P, P), for noise variance ``a`` and
        model-error variances ``b`` (C,): ``A (a J^T J + sum_c b_c J^T F_c F_c^T J + N_prior) A``.
        """
        middle = (
            noise * self.data_normal
            + np.einsum("c,cpq->pq", np.asarray(model_errors, dtype=np.float64), self.error_normals)
            + self.prior_normal
        )
        return np.asarray(self.inverse @ middle @ self.inverse)


def misfit_design_reference(
    jacobian: FloatArray, normal: FloatArray, error_columns: list[FloatArray]
) -> MisfitDesign:
    """The :class:`MisfitDesign` of one fit.

    Parameters
    ----------
    jacobian : ndarray of shape (L, P)
        Whitened Jacobian of the data part of the fit at its optimum.
    normal : ndarray of shape (P, P)
        The fit's normal matrix, priors included (``J^T J`` plus the priors' information).
    error_columns : list of C ndarrays of shape (L, Q_c)
        ``F_c``: the whitened model's derivative along each unit of each model error.
    """
    inverse = np.asarray(np.linalg.pinv(normal, hermitian=True), dtype=np.float64)
    data_normal = jacobian.T @ jacobian
    projected = jacobian @ inverse  # (L, P): the rows of H = J A J^T are projected @ J^T
    hat_diagonal = np.einsum("lp,lp->l", projected, jacobian)
    hat_square = np.einsum("lp,lp->l", projected @ data_normal, projected)
    n_params, n_components = normal.shape[0], len(error_columns)
    error_normals = np.zeros((n_components, n_params, n_params))
    error_leverages = np.zeros((jacobian.shape[0], n_components))
    error_spread = np.zeros(n_components)
    for component, columns in enumerate(error_columns):
        seen = jacobian.T @ columns  # (P, Q_c)
        absorbed = columns - projected @ seen  # Q F_c
        error_normals[component] = seen @ seen.T
        error_leverages[:, component] = np.einsum("lq,lq->l", absorbed, absorbed)
        # Q F F^T Q^T and F^T Q^T Q F share their nonzero spectrum: the smaller one.
        small = absorbed.T @ absorbed if absorbed.shape[1] <= absorbed.shape[0] else None
        gram_matrix = small if small is not None else absorbed @ absorbed.T
        error_spread[component] = float(np.sum(gram_matrix * gram_matrix))
    return MisfitDesign(
        inverse=inverse,
        data_normal=data_normal,
        prior_normal=normal - data_normal,
        error_normals=error_normals,
        noise_leverage=np.maximum(1.0 - 2.0 * hat_diagonal + hat_square, 0.0),
        error_leverages=error_leverages,
        error_spread=error_spread,
    )


@dataclass(frozen=True)
class Misfit:
    """Fitted variances of the noise and of the model errors (:func:`fit_misfit`).

    Attributes
    ----------
    noise : float
        ``a``, the whitened noise variance (1 when the noise level is known).
    model_errors : ndarray of shape (C,)
        ``b_c``, each model error's variance (0 when the residuals show none).
    dofs : ndarray of shape (C + 1,)
        Degrees of freedom behind ``a`` (inf when known) and each ``b_c``: an estimate
        ``b`` scatters like ``b chi2(nu) / nu``.
    """

    noise: float
    model_errors: FloatArray
    dofs: FloatArray


def fit_misfit(
    designs: list[MisfitDesign],
    residuals: list[FloatArray],
    noise: float | None = None,
    max_noise: float | None = None,
) -> Misfit:
    """Noise and model-error variances ``(a, b)`` from the residuals' squares (moments),
    pooled over one or more fits that share them.

    Non-negative least squares of ``r_i^2`` on ``a (Q Q^T)_ii + sum_c b_c (Q F_c F_c^T Q^T)_ii``
    (see :class:`MisfitDesign`); with ``noise`` given, ``a`` is that and only ``b`` is fitted,
    else ``a`` is fitted too, at most ``max_noise`` when given.
    A normal residual's square scatters by ``2 E^2`` around its expectation ``E``: the fit is
    reweighted by that, a few rounds from the unweighted one. The degrees of freedom of each
    variance are those of its quadratic form, ``tr(M)^2 / tr(M^2)`` with
    ``M = Q F_c F_c^T Q^T`` (Satterthwaite), and ``tr(Q Q^T)`` for the noise.

    Parameters
    ----------
    designs : list of MisfitDesign
    residuals : list of ndarrays of shape (L_j,)
        Each fit's whitened data residuals at its optimum.
    noise : float or None
    max_noise : float or None
    """
    squares = np.concatenate([np.asarray(r, dtype=np.float64) for r in residuals]) ** 2
    n_lev = np.concatenate([design.noise_leverage for design in designs])
    e_lev = np.concatenate([design.error_leverages for design in designs])
    spread = np.sum([design.error_spread for design in designs], axis=0)
    traces = e_lev.sum(axis=0)
    error_dofs = np.where(spread > 0.0, traces**2 / np.maximum(spread, 1e-300), 0.0)
    noise_dof = math.inf if noise is not None else float(n_lev.sum())
    dofs = np.r_[noise_dof, error_dofs]
    if noise is not None:
        design, target, offset = e_lev, squares - noise * n_lev, noise * n_lev
    else:
        design, target, offset = np.column_stack((n_lev, e_lev)), squares, np.zeros_like(n_lev)
    if design.shape[1] == 0 or not np.any(design):
        return Misfit(1.0 if noise is None else float(noise), np.zeros(e_lev.shape[1]), dofs)
    weights = np.ones_like(squares)
    solution = np.zeros(design.shape[1])
    for _ in range(_MISFIT_REWEIGHTS):
        solution, _ = optimize.nnls(design * weights[:, np.newaxis], target * weights)
        if noise is None and max_noise is not None and solution[0] > max_noise:
            # The noise at its bound, the model errors fitted to what is left.
            solution[0] = max_noise
            if design.shape[1] > 1:
                solution[1:], _ = optimize.nnls(
                    design[:, 1:] * weights[:, np.newaxis],
                    (target - max_noise * design[:, 0]) * weights,
                )
        expected = offset + design @ solution
        floor = 1e-3 * max(float(np.mean(expected)), 1e-300)
        weights = 1.0 / np.maximum(expected, floor)
    if noise is not None:
        return Misfit(float(noise), np.asarray(solution), dofs)
    return Misfit(float(solution[0]), np.asarray(solution[1:]), dofs)


def f2_widening(dof: FloatArray, level: float = 0.95) -> FloatArray:
    """``2 F^-1(level; 2, nu) / chi2^-1(level; 2)``: how much wider a 2-D region of ``level``
    is when its covariance rests on ``nu`` degrees of freedom (1 as ``nu`` -> inf).

    F(2, nu) has the closed-form CDF ``1 - (1 + 2 x / nu)^(-nu / 2)``, and the chi-square(2)
    quantile is ``-2 ln(1 - level)``, so the ratio is ``nu expm1(q / nu) / q`` with
    ``q = -2 ln(1 - level)`` (no distribution objects: this runs for every answer).

    Parameters
    ----------
    dof : ndarray of shape (K,)
        ``nu`` > 0.
    level : float, default=0.95

    Returns
    -------
    ndarray of shape (K,), >= 1 (inf where ``nu`` is too small for a float: a variance
    resting on next to nothing)
    """
    nu = np.asarray(dof, dtype=np.float64)
    q = -2.0 * math.log1p(-level)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        return np.asarray(np.where(nu > 0.0, nu * np.expm1(q / nu) / q, np.inf))


def predictive_covariances(
    design: MisfitDesign, misfit: Misfit, blocks: IntArray, level: float = 0.95
) -> FloatArray:
    """Covariances of some pairs of parameters (the positions), widened for the estimated
    variances behind them.

    ``V = a V_a + sum_c b_c V_c + V_prior`` (:meth:`MisfitDesign.covariance`) uses estimated
    ``a, b``, each with ``nu_c`` degrees of freedom (:class:`Misfit`). Its trace has
    ``nu = tr(V)^2 / sum_c (b_c tr(V_c))^2 / nu_c`` (Satterthwaite); with a covariance
    estimated from ``nu`` degrees of freedom, the error's Mahalanobis square over 2 is
    F(2, nu) rather than chi-square(2) / 2 distributed, so ``V`` is scaled by
    ``2 F^-1(level; 2, nu) / chi2^-1(level; 2)`` (1 when nothing is estimated): the circle of
    ``level`` then holds the truth as often as it says.

    Parameters
    ----------
    design : MisfitDesign
    misfit : Misfit
    blocks : ndarray of shape (K, 2), int
        Each pair's indices among the parameters.
    level : float, default=0.95

    Returns
    -------
    ndarray of shape (K, 2, 2)
    """
    inverse = design.inverse
    parts = [inverse @ design.data_normal @ inverse]
    parts += [inverse @ normal @ inverse for normal in design.error_normals]
    prior = inverse @ design.prior_normal @ inverse
    variances = np.r_[misfit.noise, misfit.model_errors]
    rows, cols = blocks[:, :, np.newaxis], blocks[:, np.newaxis, :]
    pieces = np.array([part[rows, cols] for part in parts])  # (C + 1, K, 2, 2)
    covariances = np.einsum("c,ckij->kij", variances, pieces) + prior[rows, cols]
    shares = variances[:, np.newaxis] * np.einsum("ckii->ck", pieces)  # (C + 1, K)
    with np.errstate(divide="ignore", invalid="ignore"):
        per_dof = np.where(
            shares > 0.0, shares**2 / np.maximum(misfit.dofs, 1e-300)[:, np.newaxis], 0.0
        )
    spread = per_dof.sum(axis=0)
    total = np.einsum("kii->k", covariances)
    widen = np.ones(blocks.shape[0])
    estimated = spread > 0.0
    if np.any(estimated):
        dof = total[estimated] ** 2 / spread[estimated]
        widen[estimated] = f2_widening(dof, level)
    # An infinite widening makes a covariance non-finite: "anywhere" once bounded
    # (bounded_covariances).
    with np.errstate(invalid="ignore"):
        return np.asarray(covariances * widen[:, np.newaxis, np.newaxis])


def own_excess_widening(
    design: MisfitDesign, residual: FloatArray, misfit: Misfit, level: float = 0.95
) -> float:
    """How much one of several fits that share pooled variances must widen its covariance
    when its own residual is beyond what those variances predict for it.

    The pooled ``(a, b)`` of :func:`fit_misfit` give each residual of this fit its expected
    square ``E_i = a (Q Q^T)_ii + sum_c b_c (Q F_c F_c^T Q^T)_ii``; their sum ``S`` scatters
    like ``S chi2(nu) / nu`` with ``nu = S^2 / sum_i E_i^2`` (Satterthwaite, the residuals
    taken as independent). A residual sum of squares ``R`` beyond its ``1 - NOISE_ONLY_P``
    quantile says this fit does not hold as well as the others (a terminal placed at the
    wrong optimum, or impaired more than the rest): its covariance is scaled by ``R / S`` (a
    Birge ratio), times :func:`f2_widening` of ``nu`` since that ratio rests on this fit's
    residuals alone. Otherwise 1.

    Parameters
    ----------
    design : MisfitDesign
        The fit's design, as passed to :func:`fit_misfit`.
    residual : ndarray of shape (L,)
        The fit's whitened data residuals.
    misfit : Misfit
        The variances pooled over all the fits.
    level : float, default=0.95

    Returns
    -------
    float, >= 1
    """
    expected_squares = (
        misfit.noise * design.noise_leverage + design.error_leverages @ misfit.model_errors
    )
    expected = float(expected_squares.sum())
    if not expected > 0.0:
        return 1.0
    observed = float(np.asarray(residual, dtype=np.float64) @ residual)
    if observed <= expected:  # below the mean, so below any upper quantile: no quantile needed
        return 1.0
    dof = expected**2 / float(np.sum(expected_squares**2))
    if observed <= expected * float(special.chdtri(dof, NOISE_ONLY_P)) / dof:
        return 1.0
    return observed / expected * float(f2_widening(np.array([dof]), level)[0])
