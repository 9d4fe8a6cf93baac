"""The covariances of the default solver's positions (docs/explanation/solver.md,
"Uncertainty"): the sandwich over the noise and the model errors the fit does not fit, its
compiled form (:mod:`._compiled.uncertainty`), and what the layout's tilt spread moves the
estimates. The variance estimates themselves are :mod:`app.vlp.uncertainty`'s.
"""

from __future__ import annotations

import math

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray, IntArray
from ...uncertainty import (
    FitQuality,
    Misfit,
    MisfitDesign,
    assess_fit,
    fit_misfit,
    misfit_design_reference,
    predictive_covariances,
)
from ._compiled import uncertainty as compiled_uncertainty
from .channel_rows import channel_rows
from .fitting import (
    Run,
    run_objective,
    whitening_of,
)
from .model import (
    Objective,
    gram,
)
from .room import MAX_MISFIT_ENTRIES, PreparedRoom
from .state import FitState
from .tolerances import ToleranceFit
from .whitening import target_gains


def response_covariances(
    normal: FloatArray,
    rows: FloatArray,
    columns: FloatArray,
    index: IntArray,
    sd: float,
) -> FloatArray:
    """Covariances (K, 2, 2) of the positions a Gauss-Newton fit moves when its whitened
    model moves by ``columns @ t`` (L, n) with ``t`` i.i.d. of standard deviation ``sd``:
    ``sd^2 G G^T`` over the rows ``index`` (K, 2) of ``G = normal^+ rows columns`` (``rows``
    the Jacobian's transpose, (P, L))."""
    moved = np.linalg.pinv(normal, hermitian=True) @ (rows @ columns)  # (P, n)
    positions = moved[index]  # (K, 2, n)
    return np.asarray(sd**2 * positions @ positions.transpose(0, 2, 1))


def misfit_design(
    jacobian: FloatArray, normal: FloatArray, columns: list[FloatArray]
) -> MisfitDesign:
    """:func:`app.vlp.uncertainty.misfit_design_reference` with the kernels in use."""
    return dispatch(misfit_design_kernel, misfit_design_reference)(jacobian, normal, columns)


def misfit_design_kernel(
    jacobian: FloatArray, normal: FloatArray, columns: list[FloatArray]
) -> MisfitDesign:
    """:func:`app.vlp.uncertainty.misfit_design_reference` in one compiled call."""
    sizes = np.array([block.shape[1] for block in columns], dtype=np.int64)
    side_by_side = np.ascontiguousarray(np.hstack(columns), dtype=np.float64)
    return MisfitDesign(
        *compiled_uncertainty.misfit_design_kernel(
            np.ascontiguousarray(jacobian, dtype=np.float64),
            np.ascontiguousarray(normal, dtype=np.float64),
            side_by_side,
            sizes,
        )
    )


def fit_uncertainty(room: PreparedRoom, run: Run, state: FitState) -> tuple[FloatArray, FitQuality]:
    """Position covariances of the final whitened fit and the fit's quality
    (docs/explanation/solver.md, "Uncertainty").

    The inverse Fisher information alone counts only the noise; a room that differs
    from its model moves the estimates further. The covariance is the sandwich
    ``A (J^T J + sum_c b_c J^T F_c F_c^T J + N_prior) A`` over the model errors the fit
    does not fit (:func:`misfit_columns`), each variance ``b_c`` estimated from the
    residuals at the optimum net of what the fitted parameters absorbed
    (:func:`app.vlp.uncertainty.fit_misfit`), then widened for those estimates' few
    degrees of freedom (:func:`app.vlp.uncertainty.predictive_covariances`). The whitened
    noise variance is fitted with them, at most 1: the whitening's noise level comes
    from the fitted noise atom, which absorbs misfit on the diagonal of ``R`` (so a room
    off its model shows a reduced chi-square below 1, not above), never less than the
    noise. A room too large to hold the model-error design falls back to inflating the
    inverse Fisher information by the reduced chi-square when above 1.
    """
    return sandwich_covariances(room, run_objective(room, run, whitening_of(room, state)), state)


def sandwich_covariances(
    room: PreparedRoom, objective: Objective, state: FitState
) -> tuple[FloatArray, FitQuality]:
    """:func:`fit_uncertainty` in the metric of ``objective``."""
    return dispatch(sandwich_covariances_kernel, sandwich_covariances_reference)(
        room, objective, state
    )


def sandwich_covariances_kernel(
    room: PreparedRoom, objective: Objective, state: FitState
) -> tuple[FloatArray, FitQuality]:
    """:func:`sandwich_covariances_reference` in one compiled call (that function for a
    channel without a compiled form, without targets, or in a room too large to hold the
    model-error design)."""
    theta = objective.pack(state)
    k = state.n_targets
    n_params, n_data = theta.shape[0], objective.data.shape[0]
    problem = objective.compiled_problem()
    small = n_data * k * room.fingerprint.n_leds <= MAX_MISFIT_ENTRIES
    if problem is None or k == 0 or not small:
        return sandwich_covariances_reference(room, objective, state)
    covariances, cost = compiled_uncertainty.sandwich_covariances_kernel(
        *problem,
        theta,
        *objective.compiled_state(state),
        room.max_noise,
        room.receivers_level,
    )
    scale = math.exp(0.5 * state.log_scale)
    return covariances, assess_fit(float(cost), n_data - n_params, scale)


def sandwich_covariances_reference(
    room: PreparedRoom, objective: Objective, state: FitState
) -> tuple[FloatArray, FitQuality]:
    """:func:`sandwich_covariances` in NumPy (:func:`gram` by the kernels in use, where the
    model-error design is too large to hold)."""
    theta = objective.pack(state)
    k = state.n_targets
    index = np.column_stack((np.arange(k), np.arange(k) + k))
    n_params, n_data = theta.shape[0], objective.data.shape[0]
    scale = math.exp(0.5 * state.log_scale)
    columns = misfit_columns(room, objective, theta, state)
    if columns is None:
        normal, _, cost = gram(objective, theta, state)
        prior = objective.prior_residuals(theta, objective.slots(k))
        fit = assess_fit(cost - float(prior @ prior), n_data - n_params, scale)
        inverse = np.linalg.pinv(normal, hermitian=True) * max(1.0, fit.chi2_per_dof)
        return np.asarray(inverse[index[:, :, None], index[:, None, :]]), fit
    augmented = objective.augmented(theta, state)
    rows = augmented[:n_params]
    residual = augmented[n_params, :n_data]
    fit = assess_fit(float(residual @ residual), n_data - n_params, scale)
    design = misfit_design_reference(rows[:, :n_data].T, rows @ rows.T, columns)
    misfit = fit_misfit([design], [residual], max_noise=room.max_noise)
    return predictive_covariances(design, misfit, index), fit


def misfit_columns(
    room: PreparedRoom, objective: Objective, theta: FloatArray, state: FitState
) -> list[FloatArray] | None:
    """Whitened derivatives of the model along the errors it does not fit: each target's
    relative amplitude error on each LED, shape (L, K M), and each target's photodiode
    tilt, shape (L, 2 K) (zeros where the layout's photodiodes are level); None when too
    large to hold (then the reduced chi-square inflates the inverse Fisher information
    instead).

    The room's residual model error (LEDs' power and beam tolerances, heights,
    reflections) scales with the signal: target k's amplitude from LED m is
    ``g_km (1 + d_km)``. A tilted photodiode moves its gains along their tilt
    derivatives, which the aggregated model does not fit. Each kind's variance is
    estimated from the residuals (:func:`app.vlp.uncertainty.fit_misfit`).
    """
    k, n_leds = state.n_targets, room.fingerprint.n_leds
    n_data = objective.data.shape[0]
    if n_data * k * n_leds > MAX_MISFIT_ENTRIES:
        return None
    gains = target_gains(room.kernel, state)  # (M, K)
    relative = np.einsum("mk,mn->kmn", gains, np.eye(n_leds))  # diag(g_k) per target
    errors = perturbation_columns(room, objective, theta, state, gains, relative)
    tilts = shape_gradients(room, state.positions, state.heights)
    if room.receivers_level:
        tilts[:, :, 1:] = 0.0  # zero columns: no variance, as the compiled kernel
    out = [errors, perturbation_columns(room, objective, theta, state, gains, tilts[:, :, 1:])]
    if objective.slots(k).n_axes != 3:  # heights held fixed
        out.append(perturbation_columns(room, objective, theta, state, gains, tilts[:, :, :1]))
    return out


def tilt_covariances(room: PreparedRoom, run: Run, state: FitState) -> FloatArray | None:
    """Position covariances from unknown photodiode tilts of the layout's spread
    (``grid.receiver_tilt_sd``), shape (K, 2, 2); None without one.

    A tilt is nearly a shift of the position, so the residuals cannot show it (the
    model-error variances of :func:`misfit_columns` stay near 0), only the layout can.

    Each target's two tilt components (radians, independent, sd ``tilt_sd``) move its
    gains along their tilt derivatives (:func:`shape_gradients`), so the whitened model
    by ``F t`` (:func:`perturbation_columns`, (L, 2 K)); the fit then moves its
    parameters by ``G t`` with ``G = (J^T J)^+ J^T F`` (a small-perturbation, Gauss-Newton
    step), and the positions' covariance is ``tilt_sd^2 G_pos G_pos^T``. Rooms too large
    to hold the model-error design (as :func:`misfit_columns`) get None.
    """
    tilt_sd = math.radians(room.fingerprint.layout.grid.receiver_tilt_sd)
    k = state.n_targets
    n_data = run.values.shape[0]
    if tilt_sd == 0 or k == 0 or n_data * k * room.fingerprint.n_leds > MAX_MISFIT_ENTRIES:
        return None
    objective = run_objective(room, run, whitening_of(room, state))
    theta = objective.pack(state)
    jacobian = objective.augmented(theta, state)[: theta.shape[0]]  # (P, L + n_prior)
    gains = target_gains(room.kernel, state)
    tilts = shape_gradients(room, state.positions, state.heights)[:, :, 1:]
    columns = perturbation_columns(room, objective, theta, state, gains, tilts)
    index = np.column_stack((np.arange(k), np.arange(k) + k))
    return response_covariances(
        jacobian @ jacobian.T, jacobian[:, :n_data], columns, index, tilt_sd
    )


def shape_gradients(room: PreparedRoom, positions: FloatArray, heights: FloatArray) -> FloatArray:
    """Derivatives of each point's gains with respect to its height and its photodiode's
    tilt (tangent components, at level), shape (K, M, 3): ``[dg/dz, dg/dtx, dg/dty]``.

    Tilting the normal ``n`` moves the line of sight ``h ∝ n . v`` by
    ``h / v_z (v_x, v_y)`` per unit of tilt (``v`` = LED minus receiver); the diffuse
    part is modelled for a level photodiode (as in :func:`.gridless.terminals.terminal_model`).
    """
    kernel = room.kernel
    k = positions.shape[0]
    xs = np.ascontiguousarray(positions[:, 0], dtype=np.float64)
    ys = np.ascontiguousarray(positions[:, 1], dtype=np.float64)
    zs = np.ascontiguousarray(heights, dtype=np.float64)
    along_z = channel_rows(kernel, xs, ys, zs, False)[3]  # (K, M)
    offsets = kernel.led_xyz[:, np.newaxis, :] - np.column_stack((positions, heights))
    drop = np.maximum(offsets[:, :, 2], 1e-9)  # (M, K)
    dist2 = np.einsum("mkc,mkc->mk", offsets, offsets)
    orders = kernel.orders[:, np.newaxis]
    los = (
        kernel.free_height_factor[:, np.newaxis]
        * drop ** (orders + 1.0)
        * dist2 ** (-(orders + 3.0) / 2.0)
        * (drop * drop >= kernel.cos_fov2 * dist2)
    )
    if kernel.has_beams:
        los = los * kernel.beam_towards(-offsets)[0]
    out = np.empty((k, kernel.n_leds, 3))
    out[:, :, 0] = along_z
    out[:, :, 1:] = ((los / drop)[:, :, np.newaxis] * offsets[:, :, :2]).transpose(1, 0, 2)
    return out


def perturbation_columns(
    room: PreparedRoom,
    objective: Objective,
    theta: FloatArray,
    state: FitState,
    gains: FloatArray,
    directions: FloatArray,
) -> FloatArray:
    """Whitened change of the model per unit of each target's gain perturbations.

    ``directions`` of shape (K, M, n): target k's gains move by ``directions[k] @ t``;
    in the aggregated correlation ``R`` moves by ``w_k (dg g_k^T + g_k dg^T)``.
    Returns shape (L, K n).
    """
    k, n_leds, n_dirs = directions.shape
    white = objective.white
    multipliers = objective._multipliers(theta, objective.slots(k), state)
    if multipliers is None:
        multipliers = np.ones(k)
    rotation = white.rotation if white.rotation is not None else np.eye(n_leds)
    rotated = (rotation.T @ gains)[:, :, np.newaxis]  # (M', K, 1)
    moved = np.einsum("ba,kbn->akn", rotation, directions)  # (M', K, n)
    if room.model == "power":
        block = 2.0 * moved * rotated
    else:
        upper, lower = white.upper, white.lower
        block = moved[upper] * rotated[lower] + rotated[upper] * moved[lower]
    block *= multipliers[np.newaxis, :, np.newaxis] * white.weights[:, np.newaxis, np.newaxis]
    return np.asarray(block.reshape(-1, k * n_dirs))


def estimable_misfit(
    misfit: Misfit,
    designs: list[MisfitDesign],
    residuals: list[FloatArray],
    noise_estimated: bool,
) -> Misfit:
    """``misfit`` with only the variances its residuals can estimate.

    The moment fit (:func:`~app.vlp.uncertainty.fit_misfit`) estimates ``v`` variances (the
    noise's when ``noise_estimated``, and each model error's that reaches the residuals)
    from residuals holding ``nu = sum_i (Q Q^T)_ii`` degrees of freedom. With fewer than two
    left over (``nu < v + 2``: one terminal of a room with five LEDs has 5 amplitudes, 2 or
    3 fitted parameters, and the variances of its tilt and height to estimate) each model
    error's estimate is chance (an F(2, nu) has no finite mean for ``nu <= 2``), and the
    covariance carries it along all that the fit absorbed, widened for its one degree of
    freedom: radii tens of times the error. Such model errors are not estimated (0); the
    noise, when estimated, then takes the whole residual, ``a = sum r^2 / nu`` on ``nu``
    degrees of freedom. The layout's declared spreads (tilt, height) reach the covariance
    through the fit's priors, not through these.

    Parameters
    ----------
    misfit : Misfit
    designs : list of MisfitDesign
        The fits' designs, as given to the moment fit.
    residuals : list of ndarrays of shape (L_j,)
        Their whitened data residuals.
    noise_estimated : bool
        Whether ``misfit.noise`` was fitted to these residuals (else known, e.g. a survey's).

    Returns
    -------
    Misfit
        ``misfit`` itself when its residuals can estimate its variances, when it holds no
        model error, or when they hold less than one degree of freedom for an estimated
        noise.
    """
    dof = float(sum(np.sum(design.noise_leverage) for design in designs))
    seen = np.sum([design.error_leverages.sum(axis=0) for design in designs], axis=0)
    estimated = int(np.count_nonzero(seen)) + int(noise_estimated)
    # (Residuals without a degree of freedom for the noise itself estimate nothing: their
    # answer rests on nothing either way, and is bounded as such.)
    if not np.any(misfit.model_errors) or dof >= estimated + 2.0 or (noise_estimated and dof < 1.0):
        return misfit
    noise, dofs = misfit.noise, misfit.dofs.copy()
    if noise_estimated:
        squares = float(sum(np.sum(np.square(r)) for r in residuals))
        noise, dofs[0] = squares / max(dof, 1e-300), dof
    return Misfit(noise, np.zeros_like(misfit.model_errors), dofs)


def answer_uncertainty(
    room: PreparedRoom, run: Run, state: FitState, tolerances: ToleranceFit | None
) -> tuple[FloatArray, FitQuality]:
    """The covariances (K, 2, 2) and fit quality of an aggregated answer: the nominal fit's
    sandwich (:func:`fit_uncertainty`), or the joint fit's own information when the room's
    tolerances were fitted (its model holds what the nominal one misses); plus what the
    layout's tilt spread moves the estimates (:func:`tilt_covariances`), unless the joint
    fit fitted the tilts (its covariances then hold them)."""
    if tolerances is None:
        covariances, fit = fit_uncertainty(room, run, state)
    else:
        covariances = tolerances.covariances
        fit = assess_fit(tolerances.chi2, tolerances.dof, math.exp(0.5 * state.log_scale))
    tilted = (
        tilt_covariances(room, run, state)
        if tolerances is None or tolerances.tilts is None
        else None
    )
    if tilted is not None:
        covariances = covariances + tilted
    return covariances, fit


def rescaled_fit(fit: FitQuality, log_scale: float) -> FitQuality:
    """``fit`` assessed again with the common scale ``log_scale`` (the search's guessed
    scale put back)."""
    return assess_fit(fit.chi2_per_dof * max(fit.dof, 1), fit.dof, math.exp(0.5 * log_scale))
