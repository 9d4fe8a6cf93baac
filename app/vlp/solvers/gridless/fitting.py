"""What every stage of the default solver calls: the per-call state (:class:`Run`), the
run's objectives and whitenings, Levenberg-Marquardt fits of all or of nearby targets, the
residuals, the noise test and the insertion scores over the grid
(docs/explanation/solver.md, "Search").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray
from ._compiled import scores as compiled_scores
from .model import (
    Objective,
    _Slots,
    fit_objective,
)
from .room import PreparedRoom
from .state import (
    FitState,
    Priors,
)
from .whitening import Whitening
from .whitening_memo import MAX_KEPT_VALUES, state_key


@dataclass
class Run:
    """Per-call state (solver objects are shared between threads, so nothing lives on room)."""

    values: FloatArray
    priors: Priors
    iterations: int = 0
    # Objectives built for this run, by (whitening, priors, ceiling) (see
    # gridless.fitting.run_objective).
    objectives: dict[tuple[int, int, float], tuple[Whitening, Priors, Objective]] = field(
        default_factory=dict, repr=False
    )
    # Profiles computed for this run's values, by the state's and the priors in force
    # (gridless.report.profiles): the search's last polish and the answer's far places
    # often ask for the same.
    profiles: dict[tuple[bytes, Priors], tuple[FloatArray, FloatArray]] = field(
        default_factory=dict, repr=False
    )
    # Each state's plug-in whitening and whitened residual, likewise
    # (gridless.fitting.whitened_residual): the escape tests and the profiles of one polished
    # fit ask for them up to four times.
    whitened: dict[tuple[bytes, Priors], tuple[Whitening, FloatArray]] = field(
        default_factory=dict, repr=False
    )


# -- main loop -----------------------------------------------------------------------
def whitening_of(room: PreparedRoom, state: FitState) -> Whitening:
    if not room.options.whiten or state.n_targets == 0:
        return room.identity
    return room.whitenings.get(state, partial(plug_in_whitening, room))


def plug_in_whitening(room: PreparedRoom, state: FitState) -> Whitening:
    return Whitening.from_state(room.model, room.kernel, state, float(state.n_targets))


def run_objective(
    room: PreparedRoom, run: Run, white: Whitening, nuisance: bool = True, ceiling: float = math.inf
) -> Objective:
    """The run's objective in ``white``'s metric, its noise coefficient at most
    ``ceiling`` (one per whitening, priors and ceiling: a solve asks for the same one many
    times, and an Objective keeps its compiled form)."""
    priors = run.priors if nuisance else room.growth_priors
    key = (id(white), id(priors), ceiling)
    known = run.objectives.get(key)
    if known is not None and known[0] is white and known[1] is priors:
        return known[2]
    objective = Objective(
        room.kernel, white, run.values, room.options.free_weights, priors, ceiling
    )
    if white.weights.shape[0] <= MAX_KEPT_VALUES:  # a large room's are computed afresh
        if len(run.objectives) >= 256:
            run.objectives.clear()
        run.objectives[key] = (white, priors, objective)
    return objective


def lm_fit(
    room: PreparedRoom,
    run: Run,
    white: Whitening,
    state: FitState,
    max_iter: int,
    nuisance: bool = True,
    around: FloatArray | None = None,
    ceiling: float = math.inf,
) -> tuple[FitState, float]:
    """LM refinement of all targets, or, with ``around`` (points, shape (n, 2), metres)
    in a large room, of the targets near those points only (:func:`lm_fit_near`); the
    noise coefficient at most ``ceiling``."""
    if around is not None:
        near = lm_fit_near(room, run, white, state, max_iter, nuisance, around, ceiling)
        if near is not None:
            return near
    state, cost, used = fit_objective(
        run_objective(room, run, white, nuisance, ceiling),
        state,
        max_iter=max_iter,
        initial_damping=room.lm.initial_damping,
        tol=room.lm.tol,
    )
    run.iterations += used
    # Per state, not per call: the answer reports the run that produced the state it
    # returns, not whichever candidate was fitted last.
    state.converged = used < max_iter
    return state, cost


def lm_fit_near(
    room: PreparedRoom,
    run: Run,
    white: Whitening,
    state: FitState,
    max_iter: int,
    nuisance: bool,
    around: FloatArray,
    ceiling: float = math.inf,
) -> tuple[FitState, float] | None:
    """LM over the positions of the targets within reach of ``around`` and the noise
    coefficient, the other targets held where they are; None when that is not the
    whole-room fit's cost with fewer parameters (a small room, nuisance parameters, a
    target off the receivers' plane) or when every target is near.

    The cost is the whole room's: the held targets' atoms are subtracted from the
    measurement, exactly. In a large room they share no LED with the changed targets,
    so their part of the gradient did not change; the final joint polish refines all.
    """
    reach = room.near_reach
    k = state.n_targets
    priors = run.priors if nuisance else room.growth_priors
    if (
        reach is None
        or k < 2
        or _Slots.make(k, priors, room.options.free_weights).size != 2 * k + 1
        or not bool(np.all(state.heights == room.kernel.receiver_height))
    ):
        return None
    offsets = state.positions[:, None, :] - np.asarray(around)[None, :, :]
    active = np.min(np.sum(offsets**2, axis=2), axis=1) <= reach**2
    if bool(active.all()):
        return None
    held = state.subset(~active)
    held.noise = 0.0
    # values - sum over the held targets of w_k phi(g(p_k)), plain units (s = 0).
    plain = Objective(room.kernel, room.identity, run.values, room.options.free_weights, Priors())
    rest = plain.residual(plain.pack(held), held)
    objective = Objective(
        room.kernel,
        white,
        rest,
        room.options.free_weights,
        priors,
        ceiling,
    )
    fitted, cost, used = fit_objective(
        objective,
        state.subset(active),
        max_iter=max_iter,
        initial_damping=room.lm.initial_damping,
        tol=room.lm.tol,
    )
    run.iterations += used
    positions = state.positions.copy()
    positions[active] = fitted.positions
    merged = FitState(
        positions,
        state.weights,
        fitted.noise,
        state.heights,
        state.log_gains,
        state.log_scale,
    )
    merged.converged = used < max_iter
    return merged, cost


def residual_of(room: PreparedRoom, run: Run, white: Whitening, state: FitState) -> FloatArray:
    if state.n_targets == 0:
        return white.data(run.values)
    return run_objective(room, run, white).data_cost(state)[1]


def noise_test(room: PreparedRoom, run: Run, state: FitState) -> tuple[Whitening, FloatArray, bool]:
    """The state's whitening and whitened residual, and whether that residual is within
    ``misfit_ratio`` times its degrees of freedom (False with none left): a complete fit
    leaves only noise, about one unit per degree of freedom."""
    white, residual = whitened_residual(room, run, state)
    return white, residual, leaves_noise(room, state, residual)


def leaves_noise(room: PreparedRoom, state: FitState, residual: FloatArray) -> bool:
    """Whether the state's whitened ``residual`` is within ``misfit_ratio`` times its
    degrees of freedom (:func:`noise_test`)."""
    dof = residual.shape[0] - 2 * state.n_targets - 1
    return bool(dof > 0 and float(residual @ residual) <= room.options.misfit_ratio * dof)


def whitened_residual(
    room: PreparedRoom, run: Run, state: FitState
) -> tuple[Whitening, FloatArray]:
    """The state's plug-in whitening and its whitened residual of the run's values, kept
    per run, state values and priors (read only: callers do not write to them)."""
    key = (state_key(state), run.priors)
    known = run.whitened.get(key)
    if known is None:
        white = whitening_of(room, state)
        known = run.whitened[key] = (white, residual_of(room, run, white, state))
    return known


def fits_to_noise(room: PreparedRoom, run: Run, state: FitState) -> bool:
    """Whether the fit leaves only noise (:func:`noise_test`): the profiles'
    likelihood-ratio regions then measure the noise, not a room that differs from its
    model (where a far move that lowers the cost follows the misfit, e.g. of a
    terminal's gain, not a target)."""
    return noise_test(room, run, state)[2]


def plain_cost(room: PreparedRoom, run: Run, state: FitState) -> float:
    residual = residual_of(room, run, room.identity, state)
    return float(residual @ residual)


def atom_energy(room: PreparedRoom, position: FloatArray, weight: float) -> float:
    g2 = room.kernel.stacked(position[None, :], with_gradients=False)[:, 0] ** 2
    if room.model == "power":
        return float(weight**2 * (g2 @ g2))
    return float(weight**2 * 0.5 * (g2.sum() ** 2 + g2 @ g2))


# -- insertion ---------------------------------------------------------------------
def grid_correlations(
    room: PreparedRoom, white: Whitening, residual: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``<c psi_j, r>`` and ``||c psi_j||^2`` for every grid point j, shapes (N,)."""
    if room.model == "power":
        weighted = white.weights * residual
        if room.dense:
            num = weighted @ room.gains_sq
            norms = (white.weights**2) @ room.gains_fourth
        else:
            num = room.squared_gains_dot(weighted)
            if white.rotation is None and np.all(white.weights == white.weights[0]):
                # Plain metric (large rooms score this way): sum_i g_ij^4, kept once.
                norms = white.weights[0] ** 2 * room.fourth_sums
            else:
                norms = room.squared_gains_dot(white.weights**2, fourth=True)
        return np.asarray(num), np.asarray(norms)
    if room.dense:
        return dispatch(correlation_scores_kernel, correlation_scores_reference)(
            room, white, residual
        )
    return correlation_scores_reference(room, white, residual)


def correlation_scores_kernel(
    room: PreparedRoom, white: Whitening, residual: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`correlation_scores_reference` of a dense room in one compiled call."""
    num, norms = compiled_scores.correlation_scores_kernel(
        white.compiled(), np.ascontiguousarray(residual, dtype=np.float64), room.gains
    )
    return num, norms


def correlation_scores_reference(
    room: PreparedRoom, white: Whitening, residual: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`grid_correlations` of the correlation model in NumPy (in a dense room, the
    reference of :func:`correlation_scores_kernel`; in a large room the only form)."""
    n_leds = room.fingerprint.n_leds
    weighted = white.weights * residual
    half = np.zeros((n_leds, n_leds))
    half[white.upper, white.lower] = weighted
    sym = 0.5 * (half + half.T)
    if white.rotation is not None:
        sym = white.rotation @ sym @ white.rotation.T
    if room.dense:
        gains = room.gains
        num = np.einsum("mj,mj->j", gains, sym @ gains)
        rot = white.rotate(gains)
        c2 = np.zeros((n_leds, n_leds))
        c2[white.upper, white.lower] = white.weights**2
        c2 = 0.5 * (c2 + c2.T)
        sq = rot**2
        norms = np.einsum("mj,mj->j", sq, c2 @ sq)
    else:
        # The operator's adjoint halves off-diagonal entries: pass 2 Q_il above the diagonal.
        upper, lower = np.triu_indices(n_leds)
        vech_q = np.where(upper == lower, 1.0, 2.0) * sym[upper, lower]
        num = room.operator.rmatvec(vech_q) / room.scale**2
        norms = room.psi_norms**2
    return np.asarray(num), np.asarray(norms)


def insertion_scores(
    room: PreparedRoom, white: Whitening, residual: FloatArray, weight: float
) -> FloatArray:
    """Decrease of the whitened cost if a target of ``weight`` were added at each grid point.

    ``2 w <c psi_j, r> - w^2 ||c psi_j||^2`` for fixed weights; the normalised correlation
    ``<c psi_j, r> / ||c psi_j||`` for free weights.
    """
    num, norms_sq = grid_correlations(room, white, residual)
    if room.options.free_weights:
        return np.asarray(num / np.sqrt(np.maximum(norms_sq, 1e-300)))
    return np.asarray(2.0 * weight * num - weight**2 * norms_sq)
