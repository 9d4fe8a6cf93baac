"""Continuous model and whitened Levenberg-Marquardt fit behind the ``gridless`` solver.

Everything here works in *normalised* units: gains are divided by ``scale``, the root of
the mean of ``(h_ij x_i)^2`` over LEDs and grid points (the SNR convention's signal
power), so a measurement ``y`` is divided by ``scale^2`` and a noise variance in these units
is ``10^(-SNR/10)``. The model of one measurement with targets at ``p_k`` is

.. math::

    \\mu(\\theta) = \\sum_k w_k \\phi(g(p_k)) + s\\, a, \\qquad
    \\phi(g) = \\mathrm{vech}(g g^T) \\text{ (correlation) or } g \\circ g \\text{ (power)},

with ``a`` the noise atom (``vech(I)`` or ones). Private: callers validate.

Speed: the solver spends its time in :meth:`Objective.augmented` and the LM loop
(:func:`.gridless.lm.levenberg_marquardt`), a few dozen small NumPy calls each, so the code
below keeps the call count low (one evaluation gives residual and Jacobian together, in-place
kernels) rather than the flop count.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray
from ._compiled import fit as compiled_fit
from ._compiled.channel import channel_constants
from .channel import ChannelKernel
from .lm import MAX_REJECTIONS, STEP_TOL_M, LMSettings, levenberg_marquardt
from .state import MAX_LOG_GAIN, MAX_LOG_SCALE, FitState, Priors
from .whitening import Whitening


@dataclass(frozen=True)
class _Slots:
    """Where each block of parameters sits in ``theta`` for K targets."""

    n_targets: int
    n_axes: int  # 2, or 3 when heights are free
    weights: slice | None
    gains: slice | None
    scale: int | None
    size: int
    n_prior: int

    @classmethod
    @functools.lru_cache(maxsize=256)  # frozen, and asked for by every new Objective
    def make(cls, n_targets: int, priors: Priors, free_weights: bool) -> _Slots:
        k = n_targets
        n_axes = 3 if priors.fits_heights else 2
        at = n_axes * k
        weights = gains = None
        scale = None
        if free_weights:
            weights, at = slice(at, at + k), at + k
        else:
            if priors.fits_gains:
                gains, at = slice(at, at + k), at + k
            if priors.fits_scale:
                scale, at = at, at + 1
        n_prior = (k if gains is not None else 0) + (1 if scale is not None else 0)
        n_prior += k if n_axes == 3 else 0
        return cls(k, n_axes, weights, gains, scale, at + 1, n_prior)


class Objective:
    """``||data - c * mu(theta)||^2 + ||prior residuals||^2`` in one whitened metric.

    Parameters are packed as ``theta = [x_1..x_K, y_1..y_K, (z_1..z_K), (w_1..w_K |
    u_1..u_K, (v)), s]``: positions, heights when free, then either free weights or the log
    amplitude gains and the common log scale, then the noise coefficient. Each target's
    atom is multiplied by ``w_k exp(v + 2 u_k)``; the priors add ``u_k / sd``, ``v / sd``
    and ``(z_k - z_0) / sd`` as pseudo-residuals (a Gaussian MAP fit).

    Parameters
    ----------
    kernel : ChannelKernel
    white : Whitening
    values : ndarray of shape (L,)
        The measurement in normalised units (not yet whitened).
    free_weights : bool
    priors : Priors, default=None
        No nuisance parameters when None.
    noise_ceiling : float, default=inf
        Upper bound of the noise coefficient ``s``.
    """

    def __init__(
        self,
        kernel: ChannelKernel,
        white: Whitening,
        values: FloatArray,
        free_weights: bool,
        priors: Priors | None = None,
        noise_ceiling: float = math.inf,
    ) -> None:
        self.kernel = kernel
        self.white = white
        self.data = white.data(values)
        self.noise_ceiling = noise_ceiling
        self.free_weights = free_weights
        self.priors = priors or Priors()
        self._slots: dict[int, _Slots] = {}
        self._bounds: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._layouts: dict[int, tuple[tuple[Any, ...], tuple[float, ...]]] = {}
        self._problem: tuple[Any, ...] | bool | None = False

    def compiled_problem(self) -> tuple[Any, ...] | None:
        """``(channel, table, white, data)`` for the compiled kernels (built once); None
        when the channel has no compiled form."""
        if self._problem is False:
            constants = channel_constants(self.kernel)
            self._problem = (
                None
                if constants is None
                else (
                    *constants,
                    self.white.compiled(),
                    np.ascontiguousarray(self.data, dtype=np.float64),
                )
            )
        assert self._problem is not True
        return self._problem

    def compiled_state(self, fixed: FitState) -> tuple[tuple[Any, ...], ...]:
        """``(fixed, layout, priors)`` tuples of the compiled kernels for ``fixed``."""
        on_plane, unit = self._state_facts(fixed)
        return (
            (
                np.ascontiguousarray(fixed.heights, dtype=np.float64),
                np.ascontiguousarray(fixed.weights, dtype=np.float64),
                np.ascontiguousarray(fixed.log_gains, dtype=np.float64),
                float(fixed.log_scale),
                on_plane,
                unit,
            ),
            *self._compiled_layout(fixed.n_targets),
        )

    def _compiled_layout(self, n_targets: int) -> tuple[tuple[Any, ...], tuple[float, ...]]:
        """The ``layout`` and ``priors`` tuples of :meth:`compiled_state` for K targets
        (kept per K: a solve fits many states of one K against one objective)."""
        found = self._layouts.get(n_targets)
        if found is None:
            slots = self.slots(n_targets)
            priors = self.priors
            found = self._layouts[n_targets] = (
                (
                    slots.n_axes,
                    -1 if slots.weights is None else int(slots.weights.start),
                    -1 if slots.gains is None else int(slots.gains.start),
                    -1 if slots.scale is None else int(slots.scale),
                    slots.n_prior,
                ),
                (
                    math.nan if priors.log_gain_sd is None else float(priors.log_gain_sd),
                    math.nan if priors.log_scale_sd is None else float(priors.log_scale_sd),
                    float(priors.height_sd),
                    float(priors.height_mean),
                ),
            )
        return found

    def slots(self, n_targets: int) -> _Slots:
        """The parameter layout for K targets."""
        found = self._slots.get(n_targets)
        if found is None:
            found = self._slots[n_targets] = _Slots.make(n_targets, self.priors, self.free_weights)
        return found

    def pack(self, state: FitState) -> FloatArray:
        """``theta`` of a state."""
        slots = self.slots(state.n_targets)
        k = slots.n_targets
        theta = np.empty(slots.size)
        theta[:k] = state.positions[:, 0]
        theta[k : 2 * k] = state.positions[:, 1]
        if slots.n_axes == 3:
            theta[2 * k : 3 * k] = state.heights
        if slots.weights is not None:
            theta[slots.weights] = state.weights
        if slots.gains is not None:
            theta[slots.gains] = state.log_gains
        if slots.scale is not None:
            theta[slots.scale] = state.log_scale
        theta[-1] = state.noise
        return theta

    def bounds(self, n_targets: int) -> tuple[FloatArray, FloatArray]:
        """Lower and upper bounds of ``theta`` (positions in the room, heights within the
        prior's bounds, gains and scale within :data:`MAX_LOG_GAIN` / :data:`MAX_LOG_SCALE`,
        weights nonnegative, noise within [0, ``noise_ceiling``]; kept per K: callers must not
        write into them)."""
        known = self._bounds.get(n_targets)
        if known is not None:
            return known
        slots = self.slots(n_targets)
        k = n_targets
        length, width = self.kernel.bounds
        lower = np.zeros(slots.size)
        upper = np.full(slots.size, np.inf)
        upper[:k] = length
        upper[k : 2 * k] = width
        if slots.n_axes == 3:
            lower[2 * k : 3 * k], upper[2 * k : 3 * k] = self.priors.height_bounds
        if slots.gains is not None:
            lower[slots.gains], upper[slots.gains] = -MAX_LOG_GAIN, MAX_LOG_GAIN
        if slots.scale is not None:
            lower[slots.scale], upper[slots.scale] = -MAX_LOG_SCALE, MAX_LOG_SCALE
        upper[-1] = self.noise_ceiling
        self._bounds[n_targets] = (lower, upper)
        return lower, upper

    def unpack(self, theta: FloatArray, state: FitState) -> FitState:
        """State of ``theta`` (what is not fitted is taken from ``state``)."""
        slots = self.slots(state.n_targets)
        k = state.n_targets
        positions = theta[: 2 * k].reshape(2, k).T.copy()
        heights = theta[2 * k : 3 * k].copy() if slots.n_axes == 3 else state.heights
        weights = theta[slots.weights].copy() if slots.weights is not None else state.weights
        log_gains = theta[slots.gains].copy() if slots.gains is not None else state.log_gains
        log_scale = float(theta[slots.scale]) if slots.scale is not None else state.log_scale
        unpacked = FitState(positions, weights, float(theta[-1]), heights, log_gains, log_scale)
        if slots.size == 2 * k + 1:  # positions and noise only: the rest is the state's
            unpacked.facts = state.facts
        return unpacked

    def _state_facts(self, fixed: FitState) -> tuple[bool, bool]:
        """Whether ``fixed`` has every target on the receivers' plane, and unit multipliers."""
        return fixed.facts_on(self.kernel.receiver_height)

    def _multipliers(self, theta: FloatArray, slots: _Slots, fixed: FitState) -> FloatArray | None:
        """Each atom's multiplier ``w_k exp(v + 2 u_k)`` at ``theta``; None when all are 1."""
        if slots.weights is not None:
            return np.asarray(theta[slots.weights])
        if slots.gains is None and slots.scale is None and self._state_facts(fixed)[1]:
            return None
        log_gains = theta[slots.gains] if slots.gains is not None else fixed.log_gains
        log_scale = theta[slots.scale] if slots.scale is not None else fixed.log_scale
        return np.asarray(fixed.weights * np.exp(log_scale + 2.0 * log_gains))

    def prior_residuals(self, theta: FloatArray, slots: _Slots) -> FloatArray:
        """The priors' pseudo-residuals at ``theta`` (empty without nuisance parameters)."""
        priors = self.priors
        parts: list[FloatArray] = []
        k = slots.n_targets
        if slots.gains is not None and priors.log_gain_sd is not None:
            parts.append(-theta[slots.gains] / priors.log_gain_sd)
        if slots.scale is not None and priors.log_scale_sd is not None:
            parts.append(np.array([-theta[slots.scale] / priors.log_scale_sd]))
        if slots.n_axes == 3:
            parts.append(-(theta[2 * k : 3 * k] - priors.height_mean) / priors.height_sd)
        return np.concatenate(parts) if parts else np.zeros(0)

    def residual(self, theta: FloatArray, fixed: FitState) -> FloatArray:
        """Whitened data residual ``c * (y - mu(theta))`` then the prior residuals.

        Parameters
        ----------
        theta : ndarray
        fixed : FitState
            Supplies what ``theta`` does not hold (fixed weights, gains, heights).
        """
        return dispatch(residual_kernel, residual_reference)(self, theta, fixed)

    def augmented(self, theta: FloatArray, fixed: FitState) -> FloatArray:
        """``[J | r]^T`` of shape (len(theta) + 1, L + n_prior): the Jacobian of the model
        (and of the priors) and the residual as rows of one array, so that one product
        gives ``J^T J``, ``J^T r`` and ``r^T r``. Rows rather than columns: every product
        below then runs on contiguous memory.
        """
        white = self.white
        slots = self.slots(fixed.n_targets)
        k, n_axes = slots.n_targets, slots.n_axes
        xs, ys = theta[:k], theta[k : 2 * k]
        # Rows [dg/dx | dg/dy | (dg/dz) | g | g | (g)] (rotated: (U^T G)^T = G^T U).
        if n_axes == 3:
            blocks = self.kernel.gradients_xyz(xs, ys, theta[2 * k : 3 * k]).T
        elif self._state_facts(fixed)[0]:
            blocks = self.kernel.gradients_xy(xs, ys).T
        else:  # heights fixed off the plane: keep the x, y gradients and two gain blocks
            full = self.kernel.gradients_xyz(xs, ys, fixed.heights).T
            blocks = np.concatenate((full[: 2 * k], full[3 * k : 5 * k]))
        if white.rotation is not None:
            blocks = blocks @ white.rotation
        left = blocks[:, white.upper]
        right = blocks[:, white.lower]
        n_grad = n_axes * k
        atoms = left[n_grad : n_grad + k] * right[n_grad : n_grad + k]  # (K, L)
        multipliers = self._multipliers(theta, slots, fixed)
        n_data = atoms.shape[1]
        n_params = theta.shape[0]
        augmented = np.empty((n_params + 1, n_data + slots.n_prior))
        data_part = augmented[:, :n_data] if slots.n_prior else augmented
        model = atoms.sum(axis=0) if multipliers is None else multipliers @ atoms
        model *= white.weights
        residual = data_part[n_params]
        np.subtract(self.data, model, out=residual)
        residual -= theta[-1] * white.weighted_diag
        # d(g_a g_b)/dp = dg_a g_b + g_a dg_b, all axes at once: rows x_1..x_K, y_1..y_K, ...
        positions = data_part[:n_grad]
        np.multiply(left[:n_grad], right[n_grad:], out=positions)
        positions += left[n_grad:] * right[:n_grad]
        if multipliers is not None:
            for axis in range(n_axes):
                positions[axis * k : (axis + 1) * k] *= multipliers[:, None]
        positions *= white.weights
        if slots.weights is not None:
            np.multiply(atoms, white.weights, out=data_part[slots.weights])
        if slots.gains is not None:
            twice = 2.0 * (np.ones(k) if multipliers is None else multipliers)
            np.multiply(atoms, twice[:, None], out=data_part[slots.gains])
            data_part[slots.gains] *= white.weights
        if slots.scale is not None:
            data_part[slots.scale] = model
        data_part[n_params - 1] = white.weighted_diag
        if slots.n_prior:
            self._fill_priors(augmented[:, n_data:], theta, slots)
        return augmented

    def _fill_priors(self, prior_part: FloatArray, theta: FloatArray, slots: _Slots) -> None:
        """The prior pseudo-residuals' columns of :meth:`augmented`."""
        k = slots.n_targets
        prior_part[:] = 0.0
        prior_part[-1] = self.prior_residuals(theta, slots)
        column = 0
        if slots.gains is not None and self.priors.log_gain_sd is not None:
            rows = np.arange(slots.gains.start, slots.gains.stop)
            prior_part[rows, column + np.arange(k)] = 1.0 / self.priors.log_gain_sd
            column += k
        if slots.scale is not None and self.priors.log_scale_sd is not None:
            prior_part[slots.scale, column] = 1.0 / self.priors.log_scale_sd
            column += 1
        if slots.n_axes == 3:
            rows = np.arange(2 * k, 3 * k)
            prior_part[rows, column + np.arange(k)] = 1.0 / self.priors.height_sd

    def data_cost(self, state: FitState) -> tuple[float, FloatArray]:
        """Cost and whitened residual of the data alone (no prior terms)."""
        residual = self.residual(self.pack(state), state)[: self.data.shape[0]]
        return float(residual @ residual), residual

    def cost(self, state: FitState) -> tuple[float, FloatArray]:
        """Cost (data and priors) and the whitened data residual of a state."""
        full = self.residual(self.pack(state), state)
        return float(full @ full), full[: self.data.shape[0]]


def residual_kernel(objective: Objective, theta: FloatArray, fixed: FitState) -> FloatArray:
    """:func:`residual_reference` in one compiled call (in NumPy without targets, or for a
    channel without a compiled form)."""
    problem = objective.compiled_problem()
    if problem is None or fixed.n_targets == 0:
        return residual_reference(objective, theta, fixed)
    return np.asarray(
        compiled_fit.residual_kernel(
            *problem,
            np.ascontiguousarray(theta, dtype=np.float64),
            *objective.compiled_state(fixed),
        )
    )


def residual_reference(objective: Objective, theta: FloatArray, fixed: FitState) -> FloatArray:
    """:meth:`Objective.residual` in plain NumPy."""
    white = objective.white
    slots = objective.slots(fixed.n_targets)
    k = slots.n_targets
    xs, ys = theta[:k], theta[k : 2 * k]
    kernel = objective.kernel
    if slots.n_axes == 3:
        gains = kernel.gains_xyz(xs, ys, theta[2 * k : 3 * k])
    elif objective._state_facts(fixed)[0]:
        gains = kernel.gains_xy(xs, ys)
    else:
        gains = kernel.gains_xyz(xs, ys, fixed.heights)
    gains = white.rotate(gains)
    atoms = gains[white.upper] * gains[white.lower]
    multipliers = objective._multipliers(theta, slots, fixed)
    model = atoms.sum(axis=1) if multipliers is None else atoms @ multipliers
    model *= white.weights
    residual = objective.data - model
    residual -= theta[-1] * white.weighted_diag
    return np.concatenate((residual, objective.prior_residuals(theta, slots)))


def fit_objective(
    objective: Objective,
    state: FitState,
    *,
    max_iter: int,
    initial_damping: float,
    tol: float,
    step_tol_m: float = STEP_TOL_M,
) -> tuple[FitState, float, int]:
    """Projected LM on an :class:`Objective` (parameters kept within their bounds): it ends
    when no target moves by ``step_tol_m`` or more, or when a step lowers, or is predicted
    to lower, the cost by less than ``tol`` of it (:class:`.gridless.lm.LMSettings`).

    The compiled fit evaluates a trial's cost alone and builds ``J^T J`` only at the
    trials it accepts, from the gains it kept (the power model's fits reject about half
    their trials); the NumPy reference computes ``J^T J`` with every trial's cost (one
    product gives both, and a second call for the Jacobian costs more there). The same
    numbers either way.

    Returns the refined state, its cost and the number of iterations used.
    """
    n_targets = state.n_targets
    lower, upper = objective.bounds(n_targets)
    theta = objective.pack(state)
    if objective.noise_ceiling < math.inf:
        # The state's noise may be above this objective's ceiling: start within the bounds.
        theta = np.clip(theta, lower, upper)
    settings = LMSettings(
        int(max_iter),
        float(initial_damping),
        MAX_REJECTIONS,
        float(tol),
        float(step_tol_m),
        2 * n_targets,
        True,
    )
    theta, cost, used = dispatch(fit_kernel, fit_reference)(
        objective, state, theta, lower, upper, settings
    )
    return objective.unpack(theta, state), cost, used


def fit_kernel(
    objective: Objective,
    state: FitState,
    theta: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float, int]:
    """:func:`fit_reference` as one compiled LM run (in NumPy without targets, or for a
    channel without a compiled form)."""
    problem = objective.compiled_problem()
    if problem is None or state.n_targets == 0:
        return fit_reference(objective, state, theta, lower, upper, settings)
    fitted, cost, used = compiled_fit.fit_kernel(
        (*problem, *objective.compiled_state(state)), theta, lower, upper, tuple(settings)
    )
    return fitted, float(cost), int(used)


def fit_reference(
    objective: Objective,
    state: FitState,
    theta: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    settings: LMSettings,
) -> tuple[FloatArray, float, int]:
    """Projected LM on ``objective`` from ``theta`` (what it does not hold from ``state``)
    within ``[lower, upper]``, in NumPy: the fitted theta, its cost and the iterations
    used."""
    fitted, cost, used, _ = levenberg_marquardt(
        lambda params: _gram_point(objective, params, state),
        lambda _params, point: point,
        theta,
        lower,
        upper,
        settings,
    )
    return fitted, float(cost), int(used)


def _gram_point(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[float, tuple[FloatArray, FloatArray]]:
    """The aggregated fit's ``evaluate``: the cost, and ``J^T J`` and ``J^T r`` as the
    point."""
    normal, gradient, cost = gram(objective, theta, fixed)
    return cost, (normal, gradient)


def gram(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[FloatArray, FloatArray, float]:
    """``J^T J``, ``J^T r`` and ``r^T r`` at ``theta`` (one BLAS call instead of three)."""
    return dispatch(gram_kernel, gram_reference)(objective, theta, fixed)


def gram_kernel(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`gram_reference` in one compiled call (in NumPy without targets, or for a
    channel without a compiled form)."""
    problem = objective.compiled_problem()
    if problem is None or fixed.n_targets == 0:
        return gram_reference(objective, theta, fixed)
    normal, gradient, cost = compiled_fit.gram_kernel(
        *problem,
        np.ascontiguousarray(theta, dtype=np.float64),
        *objective.compiled_state(fixed),
    )
    return normal, gradient, float(cost)


def gram_reference(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`gram` in plain NumPy."""
    augmented = objective.augmented(theta, fixed)
    product = augmented @ augmented.T
    n_params = theta.shape[0]
    return (
        product[:n_params, :n_params],
        product[:n_params, n_params],
        float(product[n_params, n_params]),
    )
