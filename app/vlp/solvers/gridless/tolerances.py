"""Joint fit of the aggregated correlation with the room's tolerances as nuisance parameters.

The ``gridless`` fit models every LED exactly as its layout says and every photodiode level.
Real LEDs differ from their data sheet (pilot amplitude, beam width) and hand-held
photodiodes tilt; in the aggregated correlation those errors bias every position. This
module fits them jointly with the positions, each with a Gaussian prior (a MAP fit):

.. math::

    g_{mk} = e^{a_m}\\Big(h^{los}_{mk}\\,\\frac{m_m + 1 + \\delta_m}{m_m + 1}
             \\cos^{\\delta_m}\\phi_{mk} + \\frac{h^{los}_{mk}}{D_{mk}}\\,(t_k \\cdot v_{mk})
             + h^{dif}_{mk}\\Big)

with ``a_m`` LED m's log amplitude, ``delta_m`` the change of its Lambertian order,
``phi_mk`` the irradiance angle, ``t_k`` target k's photodiode tilt (tangent components,
first order: ``n . v`` grows by ``t . v_xy``, ``D`` = the LED's height above the target),
and the model ``R = sum_k e^(v + 2 u_k) g_k g_k^T + s I`` as in :mod:`.gridless.model`. The
metric is the plug-in whitening of *this* model's gains: a whitening computed from the
nominal gains puts part of the real signal into the noise-only subspace, whose weights
are the largest, and wastes most of what the fit gains.

Private: callers validate. Used by :class:`~app.vlp.solvers.gridless.GridlessSolver` as a
last nuisance stage, kept only when it explains the data significantly better.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..._kernels import dispatch
from ...metrics import matched_errors
from ...typing import FloatArray
from ._compiled import tolerance as compiled_tolerance
from .channel import ChannelKernel
from .joint_model import (
    JointModel,
    RoomTolerances,
    joint_residual_reference,
)
from .lm import (
    PROJECTED_MAX_REJECTIONS,
    TOLERANCE_INITIAL_DAMPING,
    LMSettings,
    least_squares_normal_equations,
    least_squares_point,
    levenberg_marquardt,
)
from .state import FitState
from .whitening import Whitening

__all__ = ["GridMoves", "RoomTolerances", "ToleranceFit", "fit_room_tolerances"]

# LM for the joint fit (it runs only on measurements that show a misfit): stopped at a
# relative decrease of 1e-4 (the aggregated correlation LM's tolerance, LM_DEFAULTS).
JOINT_LM = LMSettings(
    max_iter=30,
    damping=TOLERANCE_INITIAL_DAMPING,
    max_rejections=PROJECTED_MAX_REJECTIONS,
    cost_tol=1e-4,
    step_tol=0.0,
    n_positions=0,
    before_trial=False,
)
# Re-whitening rounds: each refit uses the metric of the previous one's gains.
_ROUNDS = 2
# Iterations before a jumped fit is checked for having walked back.
_JUMP_PROBE_ITER = 2


@dataclass(frozen=True)
class GridMoves:
    """Where the joint fit may move a target to (long jumps between its local optima).

    Attributes
    ----------
    gains : ndarray of shape (M, N)
        Each grid point's nominal channel gains, in the kernel's normalised units.
    centres : ndarray of shape (N, 2), metres
        The grid points.
    min_jump : float, metres
        A moved target starts at least this far from where it was.
    height : float, metres
        A moved target's height (its own was fitted where it was): the receivers' mean.
    alternatives : tuple of ndarrays of shape (K, 2), metres
        Whole placements to try as well (other local optima of the nominal fit, such as its
        restarts'), each with the fitted tolerances, gains reset.
    split_offset : float, metres
        The brightest estimate is also tried as two, this far either side of it, the other
        estimate that explains least moved there (0: not tried).
    """

    gains: FloatArray
    centres: FloatArray
    min_jump: float
    height: float
    alternatives: tuple[FloatArray, ...] = ()
    split_offset: float = 0.0


@dataclass(frozen=True)
class ToleranceFit:
    """Result of :func:`fit_room_tolerances`.

    Attributes
    ----------
    state : FitState
        Positions, gains, scale and noise of the joint fit; heights as given, except a
        target moved far (``GridMoves.height``).
    led_log_amplitudes : ndarray of shape (M,)
    led_half_power_changes_deg : ndarray of shape (M,)
        Each LED's fitted change of Lambertian order as a change of its half-power angle,
        degrees (to first order).
    covariances : ndarray of shape (K, 2, 2), m^2
        Each position's block of the inverse of the joint fit's normal matrix (data and
        priors: the tolerances' uncertainty included), times the reduced chi-square of the
        data when above 1.
    chi2 : float
        The whitened data cost at the optimum.
    dof : int
        Its degrees of freedom: values minus positions, gains, scale and noise.
    tilts : ndarray of shape (K, 2) or None
        Each photodiode's fitted tilt (tangent components, about radians); None where the
        tilts were not fitted (then the covariances do not hold them).
    """

    state: FitState
    led_log_amplitudes: FloatArray
    led_half_power_changes_deg: FloatArray
    covariances: FloatArray
    chi2: float
    dof: int
    tilts: FloatArray | None = None


def _jumps(
    model: JointModel,
    theta: FloatArray,
    noise: float,
    values: FloatArray,
    white: Whitening,
    moves: GridMoves,
) -> tuple[FloatArray, Whitening, JointModel]:
    """Move each target in turn far (at least ``moves.min_jump``) to where the residual left
    by the others asks for one, or else to where the whole residual does, refit everything,
    keep the move when it lowers the cost; then try ``moves.alternatives`` the same way.

    Under the room's tolerances the aggregated fit has optima in which two estimates share
    one terminal and another terminal has none. The nominal model cannot tell them from the
    right one (their costs agree within its misfit); the joint fit can. ADCG's relocation in
    the nominal fit moves a target to the best point of the residual, which is next to where
    it was; here the best point at least ``min_jump`` away, or the point where a terminal is
    missing. Most moved targets walk back (or another target takes their place) within a few
    iterations: such moves stop there. A moved target starts at ``moves.height``; the model
    returned holds the heights of the fit returned.
    """
    k, m = model.n_targets, model.n_leds
    # The metric the fit was refined in last (``theta`` is its optimum): moves are compared
    # in it.
    data = white.data(values)
    residual, _ = model.residual_and_jacobian(theta, white, data)
    cost = start_cost = float(residual @ residual)
    measured = np.zeros((m, m))
    measured[model.upper, model.lower] = values
    measured[model.lower, model.upper] = values
    rotation = white.rotation
    assert rotation is not None
    # The whitened cost sums each entry (a <= b) of U^T E U once, weighted c^2: as a full
    # symmetric sum, off-diagonal entries count half.
    entry_weights = np.zeros((m, m))
    entry_weights[white.upper, white.lower] = white.weights**2
    entry_weights[white.lower, white.upper] = white.weights**2
    entry_weights *= np.where(np.eye(m, dtype=bool), 1.0, 0.5)

    def scan(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
        """The targets' gains, multipliers and positions, the grid's gains (with the fitted
        LED amplitudes, in the metric's basis) and their whitened energies, the unit."""
        gains, multipliers, _ = model.gains(theta)
        positions, _, log_scale, amps, *_ = model.split(theta)
        grid = rotation.T @ (np.exp(amps)[:, np.newaxis] * moves.gains)
        grid_energy = np.sum(grid**2 * (entry_weights @ grid**2), axis=0)
        return gains * np.sqrt(multipliers), positions, grid, grid_energy, math.exp(log_scale)

    def scores(others: FloatArray) -> FloatArray:
        signal = scaled[:, others] @ scaled[:, others].T
        left = rotation.T @ (measured - signal - theta[-1] * np.eye(m)) @ rotation
        # Each grid point's decrease of the cost with a target of unit gain there.
        score = 2.0 * unit * np.sum(grid * ((left * entry_weights) @ grid), axis=0)
        return np.asarray(score - unit**2 * grid_energy)

    def explained(theta: FloatArray) -> FloatArray:
        """Each target's share of the fit: the whitened data cost with its atom left out."""
        scaled = scan(theta)[0]
        base = measured - scaled @ scaled.T - theta[-1] * np.eye(m)
        shares = np.empty(k)
        for target in range(k):
            left = rotation.T @ (base + np.outer(scaled[:, target], scaled[:, target])) @ rotation
            shares[target] = float(np.sum(left**2 * entry_weights))
        return shares

    scaled, positions, grid, grid_energy, unit = scan(theta)
    # The best point of the whole residual: where a terminal is missing.
    missing = int(np.argmax(scores(np.ones(k, dtype=bool))))
    for target in range(k):
        far = np.linalg.norm(moves.centres - positions[target], axis=1) > moves.min_jump
        # Two places to try: the best far point of the residual the others leave, then the
        # missing terminal's point if far enough.
        own = int(np.argmax(np.where(far, scores(np.arange(k) != target), -np.inf)))
        candidate = model
        if model.heights[target] != moves.height:
            heights = model.heights.copy()
            heights[target] = moves.height
            candidate = model.with_heights(heights)
        for best in [own] if missing == own or not far[missing] else [own, missing]:
            if not far[best]:
                continue
            moved = theta.copy()
            moved[target], moved[k + target] = moves.centres[best]
            moved[2 * k + target] = 0.0
            tried = _try_move(candidate, cost, moved, white, data, positions)
            if tried is not None:
                (theta, cost), model = tried, candidate
                scaled, positions, grid, grid_energy, unit = scan(theta)
                missing = int(np.argmax(scores(np.ones(k, dtype=bool))))
                break
    if moves.split_offset > 0.0 and k >= 2:
        split = _split_brightest(model, theta, cost, white, data, moves.split_offset, explained)
        if split is not None:
            theta, cost = split
            positions = model.split(theta)[0]
    for placement in moves.alternatives:
        level = np.all(model.heights == moves.height)
        candidate = model if level else model.with_heights(np.full(k, moves.height))
        moved = theta.copy()
        moved[:k], moved[k : 2 * k] = placement[:, 0], placement[:, 1]
        moved[2 * k : 3 * k] = 0.0
        tried = _try_move(candidate, cost, moved, white, data, positions)
        if tried is not None:
            (theta, cost), model = tried, candidate
            positions = model.split(theta)[0]
    if cost < start_cost:  # moved: one more round in the new fit's metric
        white = model.whitening(theta, noise)
        theta, _ = _fit_joint(model, theta, white, white.data(values))
    return theta, white, model


def _split_brightest(
    model: JointModel,
    theta: FloatArray,
    cost: float,
    white: Whitening,
    data: FloatArray,
    offset: float,
    explained: Callable[[FloatArray], FloatArray],
) -> tuple[FloatArray, float] | None:
    """The fit with the brightest estimate tried as two (``offset`` either side of it, along
    x then y) and the estimate whose atom the fit misses least moved next to it, with its cost
    when it lowers ``cost``; None when no estimate is brighter than half its gain prior's sd
    or no split lowers the cost.

    Two terminals closer than the beams can separate can be fitted as one estimate of
    higher gain (the gain prior holds it near 1, so it sits between them), another estimate
    taking the spare signal elsewhere. The long moves do not find the pair: the merged
    estimate leaves little residual where the second terminal is.
    """
    k = model.n_targets
    positions, log_gains, *_ = model.split(theta)
    brightest = int(np.argmax(log_gains))
    if log_gains[brightest] <= 0.5 / model.prior_inverse_sd[0]:
        return None
    shares = explained(theta)
    shares[brightest] = np.inf
    spare = int(np.argmin(shares))  # left out, the cost rises least
    centre = positions[brightest]
    lower, upper = model.bounds()
    for step in offset * np.eye(2):
        moved = theta.copy()
        moved[spare], moved[k + spare] = centre + step
        moved[brightest], moved[k + brightest] = centre - step
        moved[2 * k + spare] = moved[2 * k + brightest] = 0.0
        moved = np.clip(moved, lower, upper)
        tried = _try_move(model, cost, moved, white, data, positions)
        if tried is not None:
            return tried
    return None


def _try_move(
    model: JointModel,
    cost: float,
    moved: FloatArray,
    white: Whitening,
    data: FloatArray,
    positions: FloatArray,
) -> tuple[FloatArray, float] | None:
    """The fit from ``moved`` and its cost when it lowers ``cost``, the current fit's (its
    targets at ``positions``), else None. After a few iterations a fit that has come back
    closer to the current placement than to where it started is dropped: most moves walk
    back into the basin already fitted."""
    start = model.split(moved)[0]
    moved, _ = _fit_joint(model, moved, white, data, _JUMP_PROBE_ITER)
    probe = model.split(moved)[0]
    if matched_errors(probe, positions).max() < matched_errors(probe, start).max():
        return None
    moved, moved_cost = _fit_joint(model, moved, white, data)
    return (moved, moved_cost) if moved_cost < cost else None


def _fit_joint(
    model: JointModel,
    theta: FloatArray,
    white: Whitening,
    data: FloatArray,
    max_iter: int = JOINT_LM.max_iter,
) -> tuple[FloatArray, float]:
    """The joint fit from ``theta``: its fitted theta and cost."""
    settings = JOINT_LM._replace(max_iter=max_iter)
    lower, upper = model.bounds()
    return dispatch(joint_fit_kernel, joint_fit_reference)(
        model, theta, white, data, lower, upper, settings
    )


def joint_fit_kernel(
    model: JointModel,
    theta: FloatArray,
    white: Whitening,
    data: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float]:
    """:func:`joint_fit_reference` as one compiled LM run (in NumPy for a channel without a
    compiled form)."""
    compiled_model = model.compiled_model(white, data)
    if compiled_model is None:
        return joint_fit_reference(model, theta, white, data, lower, upper, settings)
    fitted, cost = compiled_tolerance.joint_fit_kernel(
        compiled_model,
        np.array(theta, dtype=np.float64, order="C", copy=True),
        lower,
        upper,
        tuple(settings),
    )
    return fitted, float(cost)


def joint_fit_reference(
    model: JointModel,
    theta: FloatArray,
    white: Whitening,
    data: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float]:
    """Projected LM on the joint model from ``theta`` within ``[lower, upper]`` in the
    metric ``white`` (``data`` whitened), in NumPy: the fitted theta and its cost."""

    def evaluate(params: FloatArray) -> tuple[float, tuple[FloatArray, FloatArray]]:
        residual, jacobian = joint_residual_reference(model, params, white, data)
        return least_squares_point(residual, jacobian)

    fitted, cost, _, _ = levenberg_marquardt(
        evaluate, least_squares_normal_equations, theta, lower, upper, settings
    )
    return fitted, cost


def fit_room_tolerances(
    kernel: ChannelKernel,
    values: FloatArray,
    state: FitState,
    priors: tuple[float, float],
    tolerances: RoomTolerances,
    significance: float,
    moves: GridMoves | None = None,
    score_ratio: float = 1.0,
    tilt_stage_sd: float = 0.0,
) -> ToleranceFit | None:
    """MAP fit of positions, gains, scale, noise and the room's tolerances (module doc).

    Gated, because fitted always the extra parameters ``n`` (each LED's amplitude and beam,
    the tilts when fitted, the gains and the scale, freed here even when the fit without
    tolerances held them) fit the noise of a room exactly as modelled:

    - a score test first: the first Gauss-Newton step must promise a decrease above
      ``score_ratio`` times ``n`` (in a room as modelled it promises about half of ``n``:
      the priors shrink the step); else None, with no fit;
    - the first round runs in the starting state's own metric, where the fit without
      tolerances is at its optimum, and must lower the cost by more than
      ``n + significance sqrt(2 n)``, the chi-square of ``n`` parameters by chance; else None.

    Then more rounds follow, each in the metric of the previous one's gains, the long moves,
    and (``tilt_stage_sd``) a stage with the photodiodes' tilts.

    Parameters
    ----------
    kernel : ChannelKernel
    values : ndarray of shape (M (M + 1) / 2,)
        ``vech(R)`` in the kernel's normalised units.
    state : FitState
        The fit without tolerances (its unit weights, heights kept).
    priors : (float, float)
        Prior sds of each target's log gain and of the common log scale.
    tolerances : RoomTolerances
    significance : float
        Standard deviations of the chance decrease the first round must beat.
    moves : GridMoves, optional
        Long moves of each target tried after the rounds (None: none).
    score_ratio : float, default=1.0
        The score test's bar, in units of the extra parameters' count.
    tilt_stage_sd : float, default=0.0
        When the fit is kept and ``tolerances`` hold no tilts: each photodiode's tilt is then
        fitted too, from the joint optimum, with this prior sd per tangent component (about
        radians); 0: not.

    Returns
    -------
    ToleranceFit or None
    """
    model = JointModel(kernel, np.asarray(state.heights, dtype=np.float64), priors, tolerances)
    start = model.pack(state)
    extra = model.size() - 2 * model.n_targets - 1  # all but the positions and the noise
    # The noise level of the metric stays the fit's without tolerances: refitted with 2 M
    # more parameters, s shrinks with what they absorb, and a metric whitened by the
    # smaller s would weight the next round's residuals up (in trials of an ideal room,
    # each round's cost grew tenfold and the positions drifted by decimetres).
    noise = float(state.noise)
    white = model.whitening(start, noise)
    data = white.data(values)
    base_residual, jacobian = model.residual_and_jacobian(start, white, data)
    base_cost = float(base_residual @ base_residual)
    # Score test first (one evaluation): the decrease the Gauss-Newton step promises. A
    # room as modelled rarely promises enough, and then no LM runs.
    gradient = jacobian.T @ base_residual
    try:
        promised = float(gradient @ np.linalg.solve(jacobian.T @ jacobian, gradient))
    except np.linalg.LinAlgError:
        promised = math.inf
    if not promised > score_ratio * extra:
        return None
    theta, cost = _fit_joint(model, start, white, data)
    if not base_cost - cost > extra + significance * math.sqrt(2.0 * extra):
        return None
    for _ in range(_ROUNDS - 1):
        white = model.whitening(theta, noise)
        theta, _ = _fit_joint(model, theta, white, white.data(values))
    if moves is not None:
        theta, white, model = _jumps(model, theta, noise, values, white, moves)
    if tilt_stage_sd > 0 and model.n_tilts == 0:
        # Hand-held photodiodes tilt. Fitted from the start, the tilts (nearly shifts of the
        # positions) widen the gate's bar and the moves' reach, and many placements lost the
        # whole joint fit; added here, from its optimum, they refine it. Not gated: a tilt
        # lowers the cost little whether it is there or not
        # (docs/decisions/tilts-after-tolerances.md), so only
        # the layout (receivers_level) can say there is none.
        model = JointModel(
            kernel, model.heights, priors, replace(tolerances, tilt_sd=tilt_stage_sd)
        )
        theta = np.concatenate((theta[:-1], np.zeros(model.n_tilts), theta[-1:]))
        for _ in range(_ROUNDS):
            white = model.whitening(theta, noise)
            theta, _ = _fit_joint(model, theta, white, white.data(values))
    residual, jacobian = model.residual_and_jacobian(theta, white, white.data(values))
    n_data, k = white.weights.shape[0], model.n_targets
    chi2 = float(residual[:n_data] @ residual[:n_data])
    dof = max(n_data - 3 * k - 2, 1)
    inverse = np.linalg.pinv(jacobian.T @ jacobian, hermitian=True) * max(1.0, chi2 / dof)
    index = np.column_stack((np.arange(k), np.arange(k) + k))
    covariances = inverse[index[:, :, np.newaxis], index[:, np.newaxis, :]]
    positions, log_gains, log_scale, amps, order_changes, tilts, noise = model.split(theta)
    fitted = FitState(
        positions.copy(),
        state.weights.copy(),
        noise,
        np.array(model.heights, dtype=np.float64),
        log_gains.copy(),
        log_scale,
    )
    return ToleranceFit(
        fitted,
        amps.copy(),
        -np.degrees(order_changes / np.maximum(model.order_per_radian, 1e-12)),
        np.asarray(covariances),
        chi2,
        dof,
        tilts.T.copy() if model.n_tilts else None,
    )
