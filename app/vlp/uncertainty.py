"""How much to trust an answer: confidence radii and the goodness of a fit.

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

import functools
import math
from dataclasses import dataclass
from typing import Literal, cast

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
    "bounded_covariances",
    "confidence_radii",
    "confidence_radius",
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
# Gauss-Legendre nodes and weights on [-pi/2, pi/2] for the radial probability below.
_NODES, _UNIT_WEIGHTS = np.polynomial.legendre.leggauss(96)
_ANGLES = 0.5 * math.pi * _NODES
_WEIGHTS = 0.5 * math.pi * _UNIT_WEIGHTS
_SINES = np.sin(_ANGLES)
_COSINES = np.cos(_ANGLES)
_ROOT_TWO_PI = math.sqrt(2.0 * math.pi)
# Newton on the radial probability: stop when it is this close to the level (a radius to
# ~1e-13 relative); the bracket bounds the steps whatever happens.
_RADIUS_TOLERANCE = 1e-14
# A 2 x 2 covariance is taken as one while its determinant is above this times its trace
# squared (about the ratio of its eigenvalues: standard deviations 1e6 apart). Below it
# a direction had no information: a pseudo-inverse gives it 0, not infinity (a receiver
# that sees one LED lies on a ring around it, and the ring's tangent came out "exact").
_MIN_EIGENVALUE_RATIO = 1e-12
_MAX_RADIUS_STEPS = 60
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


def confidence_radius(covariance: FloatArray, level: float = 0.95) -> float:
    """Radius of the circle around the estimate that holds the truth with ``level``.

    One covariance; see :func:`confidence_radii` for the method.

    Parameters
    ----------
    covariance : ndarray of shape (2, 2), m^2
    level : float, default=0.95

    Returns
    -------
    radius : float, metres

    Examples
    --------
    >>> round(confidence_radius(np.eye(2) * 0.01), 4)  # sqrt(-2 ln 0.05) * 0.1
    0.2448
    """
    covariance = np.asarray(covariance, dtype=np.float64)
    return float(confidence_radii(covariance[np.newaxis], level)[0])


def confidence_radii(covariances: FloatArray, level: float = 0.95) -> FloatArray:
    """Radii of the circles around the estimates that hold the truth with ``level``.

    For a zero-mean 2-D Gaussian error with covariance eigenvalues ``l1 >= l2``,
    ``|e|^2 = l1 X^2 + l2 Y^2`` with X, Y independent standard normals. With ``r = sqrt(l1) u``,
    ``rho = l2 / l1`` and ``X = u sin(t)``:
    ``P(|e| <= r) = int_{-pi/2}^{pi/2} phi(u sin t) (2 Phi(u cos(t) / sqrt(rho)) - 1) u cos(t) dt``
    (Gauss-Legendre). All estimates are solved together for ``u`` by Newton's method on that
    quadrature, with its exact derivative, kept inside a shrinking bracket (bisection when a
    step leaves it). An answer asks for one radius per estimate, so this runs on every
    localize request.

    Parameters
    ----------
    covariances : ndarray of shape (K, 2, 2), m^2
    level : float, default=0.95

    Returns
    -------
    radii : ndarray of shape (K,), metres (inf for a non-finite covariance, 0 for a zero one)
    """
    cov = np.asarray(covariances, dtype=np.float64)
    if cov.ndim != 3 or cov.shape[1:] != (2, 2):
        raise ValueError(f"covariances must have shape (K, 2, 2), got {cov.shape}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if cov.shape[0] == 0:
        return np.zeros(0)
    # The kernel engine is imported here, not at the top: numba loads with the first
    # radius, not with this module.
    from ._kernels import dispatch

    # P(0) = 0 < level and P(two_d) >= level (rho <= 1): a bracket for every estimate.
    one_d, two_d = _radial_bracket(float(level))
    return dispatch(covariance_radii_kernel, covariance_radii_reference)(
        cov, float(level), one_d, two_d
    )


@functools.lru_cache(maxsize=8)
def _radial_bracket(level: float) -> tuple[float, float]:
    """``u`` of the ``level`` radius when ``rho -> 0`` and when ``rho = 1`` (Rayleigh): the
    bounds of every estimate's root (:func:`covariance_radii_reference`)."""
    return float(special.ndtri(0.5 + 0.5 * level)), math.sqrt(-2.0 * math.log1p(-level))


def covariance_radii_kernel(
    covariances: FloatArray, level: float, one_d: float, two_d: float
) -> FloatArray:
    """:func:`covariance_radii_reference` compiled (:mod:`app.vlp._radii_compiled`: one
    call per answer; each estimate's eigenvalues in closed form, as LAPACK's for a 2 x 2
    matrix, and its own Newton iteration to the tolerance)."""
    from . import _radii_compiled

    return cast(
        "FloatArray",
        _radii_compiled.covariance_radii_kernel(
            np.ascontiguousarray(covariances, dtype=np.float64),
            level,
            one_d,
            two_d,
            (_WEIGHTS, _SINES, _COSINES),
            _RADIUS_TOLERANCE,
            _MAX_RADIUS_STEPS,
        ),
    )


def covariance_radii_reference(
    covariances: FloatArray, level: float, one_d: float, two_d: float
) -> FloatArray:
    """:func:`confidence_radii` of validated covariances (K, 2, 2), K >= 1, in NumPy: each
    symmetrised covariance's eigenvalues ``l2 <= l1``, then ``u`` per estimate with
    ``P(|e| <= u sqrt(l1)) = level`` for ``rho = l2 / l1`` by Newton's method kept inside
    the bracket ``[0, two_d]``, from between the one- and two-dimensional roots
    (``one_d``, ``two_d``), on the radial probability by Gauss-Legendre quadrature."""
    finite = np.all(np.isfinite(covariances), axis=(1, 2))
    radii = np.where(finite, 0.0, math.inf)
    eigen = np.zeros((covariances.shape[0], 2))
    kept = covariances[finite]
    eigen[finite] = np.linalg.eigvalsh(0.5 * (kept + kept.transpose(0, 2, 1)))
    major = eigen[:, 1]
    solve = finite & (major > 0.0)
    if not np.any(solve):
        return radii
    major = major[solve]
    root_ratio = np.sqrt(np.maximum(eigen[solve, 0] / major, 1e-300))
    ratio = root_ratio[:, np.newaxis]
    low = np.zeros(root_ratio.size)
    high = np.full(root_ratio.size, two_d * 1.01)
    reach = one_d + (two_d - one_d) * root_ratio  # within a few % of the root
    for _ in range(_MAX_RADIUS_STEPS):
        u = reach[:, np.newaxis]
        along = u * _SINES
        across = u * _COSINES / ratio
        density = np.exp(-0.5 * along**2) / _ROOT_TWO_PI
        inner = 2.0 * special.ndtr(across) - 1.0
        excess = np.sum(_WEIGHTS * density * inner * u * _COSINES, axis=1) - level
        slope = np.sum(
            _WEIGHTS
            * _COSINES
            * density
            * (
                (1.0 - along**2) * inner
                + u * (2.0 / _ROOT_TWO_PI) * np.exp(-0.5 * across**2) * _COSINES / ratio
            ),
            axis=1,
        )
        if np.all(np.abs(excess) <= _RADIUS_TOLERANCE):
            break
        low = np.where(excess < 0.0, reach, low)
        high = np.where(excess > 0.0, reach, high)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = reach - excess / slope
        inside = (slope > 0.0) & (step > low) & (step < high)
        reach = np.where(inside, step, 0.5 * (low + high))
    radii[solve] = np.sqrt(major) * reach
    return radii


def bounded_covariances(
    covariances: FloatArray, max_radius: float, level: float = 0.95
) -> FloatArray:
    """Covariances scaled down, each as a whole, so that no ``level`` radius exceeds
    ``max_radius``.

    An estimate and its target both lie on the room's floor, so a confidence circle wider
    than the floor's diagonal says no more than the diagonal itself: it holds the truth in
    any case. Fits that the data barely determine (the power model's ``M`` values for ``K``
    targets with ``2 K + 1 > M`` unknowns) have a singular information and so covariances of
    round-off size, and sometimes, computed in that round-off, no covariance at all (a
    negative variance); bounded, they say "anywhere in the room" in numbers a client can
    use. A covariance times ``c`` has its radius times ``sqrt(c)``, so the shape is kept.
    A singular one (smaller eigenvalue below 1e-12 of the larger, zero included) says
    nothing either: the direction it calls exact is the one the fit had no information on,
    which a pseudo-inverse sets to 0.

    Parameters
    ----------
    covariances : ndarray of shape (K, 2, 2), m^2
    max_radius : float, metres, positive
    level : float, default=0.95

    Returns
    -------
    bounded : ndarray of shape (K, 2, 2), m^2 (what is no covariance, non-finite, singular
        or indefinite, becomes the circle of radius ``max_radius``)

    Examples
    --------
    >>> bounded = bounded_covariances(np.eye(2)[np.newaxis] * 1e20, 5.0)
    >>> round(float(confidence_radii(bounded)[0]), 6)
    5.0
    """
    if not (math.isfinite(max_radius) and max_radius > 0.0):
        raise ValueError(f"max_radius must be positive and finite, got {max_radius}")
    bounded = np.array(covariances, dtype=np.float64)
    # The circle of radius r holds 1 - exp(-r^2 / (2 s)) of N(0, s I), and a covariance
    # below s I has a smaller radius: only those with a trace above s can be too wide.
    circle = max_radius**2 / (-2.0 * math.log1p(-level))
    if all(_inside_circle(covariance, circle) for covariance in bounded.tolist()):
        return bounded  # the common case, once per answer: nothing to bound
    with np.errstate(invalid="ignore", over="ignore"):
        first, second = bounded[:, 0, 0], bounded[:, 1, 1]
        cross = 0.5 * (bounded[:, 0, 1] + bounded[:, 1, 0])
        product = first * second
        valid = (
            np.all(np.isfinite(bounded), axis=(1, 2))
            & (first >= 0.0)
            & (second >= 0.0)
            & (product - cross**2 > _MIN_EIGENVALUE_RATIO * (first + second) ** 2)
        )
        trace = np.where(valid, first + second, 0.0)
    if valid.all() and float(trace.max(initial=0.0)) <= circle:
        return bounded  # the common case, once per answer: nothing to bound
    check = valid & (trace > circle)
    if np.any(check):
        radii = confidence_radii(bounded[check], level)
        factors = np.minimum(1.0, max_radius / radii) ** 2
        bounded[check] *= factors[:, np.newaxis, np.newaxis]
    bounded[~valid] = circle * np.eye(2)
    return bounded


def _inside_circle(covariance: list[list[float]], circle: float) -> bool:
    """Whether one covariance (2 x 2, as lists) is one that :func:`bounded_covariances`
    leaves as it is: finite, not singular nor indefinite, with a trace of at most
    ``circle``. In Python floats, the same operations as the vectorised test: an answer's
    few estimates cost less so."""
    (first, xy), (yx, second) = covariance
    cross = 0.5 * (xy + yx)
    trace = first + second
    return (
        math.isfinite(first)
        and math.isfinite(xy)
        and math.isfinite(yx)
        and math.isfinite(second)
        and first >= 0.0
        and second >= 0.0
        and first * second - cross * cross > _MIN_EIGENVALUE_RATIO * (trace * trace)
        and trace <= circle
    )


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
