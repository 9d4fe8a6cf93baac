"""Continuous model and whitened Levenberg-Marquardt fit behind the ``gridless`` solver.

Everything here works in *normalised* units: gains are divided by ``scale``, the root of
the mean of ``(h_ij x_i)^2`` over LEDs and grid points (the SNR convention's signal
power), so a measurement ``y`` is divided by ``scale^2`` and a noise variance in these units
is ``10^(-SNR/10)``. The model of one measurement with targets at ``p_k`` is

.. math::

    \\mu(\\theta) = \\sum_k w_k \\phi(g(p_k)) + s\\, a, \\qquad
    \\phi(g) = \\mathrm{vech}(g g^T) \\text{ (correlation) or } g \\circ g \\text{ (power)},

with ``a`` the noise atom (``vech(I)`` or ones). Private: callers validate.

Speed: the solver spends its time in :meth:`Objective.augmented` and the LM loop, a few
dozen small NumPy calls each, so the code below keeps the call count low (one evaluation
gives residual and Jacobian together, in-place kernels, LAPACK's ``posv`` for the damped
normal equations) rather than the flop count.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.linalg import lapack

from ..._kernels import kernel_mode
from ...measurements import Model
from ...typing import FloatArray, IntArray
from ._compiled.channel import channel_constants
from ._compiled.fit import (
    gram_kernel,
    lm_kernel,
    residual_kernel,
    whiten_kernel,
    whitening_kernel,
)
from .channel import ChannelKernel
from .lm import (
    DAMPING_DOWN,
    DAMPING_SINGULAR,
    DAMPING_UP,
    DIAGONAL_FLOOR,
    EIG_FLOOR,
    MAX_REJECTIONS,
    MIN_DAMPING,
    SIGMA2_FLOOR,
    STEP_TOL_M,
)

# Smallest noise variance assumed when whitening relative to the mean received power (1e-4:
# an SNR of 40 dB; the absolute floor is SIGMA2_FLOOR).
_SIGMA2_REL_FLOOR = 1e-4
# Whitened measurements of at most this many values are kept by their Whitening.
_KEPT_DATA_MAX = 4096


@dataclass(frozen=True)
class Priors:
    """Gaussian priors of the nuisance parameters; a None standard deviation = not fitted.

    Attributes
    ----------
    log_gain_sd : float or None
        Standard deviation of each target's log amplitude gain ``u_k`` (mean 0).
    log_scale_sd : float or None
        Standard deviation of the common log power scale ``v`` (mean 0).
    height_sd : float
        Standard deviation of each target's height around ``height_mean``, metres; 0 keeps
        every target on the receivers' plane.
    height_mean : float
        The receivers' nominal height, metres.
    height_bounds : tuple of float
        Heights are kept within these, metres.
    """

    log_gain_sd: float | None = None
    log_scale_sd: float | None = None
    height_sd: float = 0.0
    height_mean: float = 0.0
    height_bounds: tuple[float, float] = (0.0, 0.0)

    @property
    def fits_gains(self) -> bool:
        """True when each target's gain is a parameter."""
        return self.log_gain_sd is not None

    @property
    def fits_scale(self) -> bool:
        """True when the common scale is a parameter."""
        return self.log_scale_sd is not None

    @property
    def fits_heights(self) -> bool:
        """True when each target's height is a parameter."""
        return self.height_sd > 0.0


# Log amplitude gains are kept within +-ln 2 (a terminal between half and twice the modelled
# gain) and the log power scale within +-ln 10^4 (beyond, the measurement is refused).
MAX_LOG_GAIN = math.log(2.0)
MAX_LOG_SCALE = math.log(1e4)


@dataclass
class FitState:
    """Current estimate.

    Attributes
    ----------
    positions : ndarray of shape (K, 2), metres
    weights : ndarray of shape (K,)
        Fixed (or, with free weights, fitted) multipliers of each target's atom.
    noise : float
        Noise coefficient s (normalised units).
    heights : ndarray of shape (K,), metres
    log_gains : ndarray of shape (K,)
        Each target's log amplitude gain ``u_k``.
    log_scale : float
        The common log power scale ``v``.
    converged : bool
        Whether the Levenberg-Marquardt run that produced this state stopped by its
        tolerance (or at a local minimum) rather than by running out of iterations.
    """

    positions: FloatArray
    weights: FloatArray
    noise: float
    heights: FloatArray
    log_gains: FloatArray
    log_scale: float = 0.0
    # (all on the receivers' plane, unit multipliers), filled by the objective on first use.
    facts: tuple[bool, bool] | None = field(default=None, compare=False, repr=False)
    converged: bool = field(default=True, compare=False, repr=False)

    @classmethod
    def empty(cls, log_scale: float = 0.0) -> FitState:
        """No targets yet."""
        return cls(np.zeros((0, 2)), np.zeros(0), 0.0, np.zeros(0), np.zeros(0), log_scale)

    @property
    def n_targets(self) -> int:
        """K."""
        return int(self.positions.shape[0])

    def effective_weights(self) -> FloatArray:
        """``w_k exp(v + 2 u_k)``: each atom's multiplier in the model."""
        return np.asarray(self.weights * np.exp(self.log_scale + 2.0 * self.log_gains))

    def subset(self, keep: npt.NDArray[np.bool_] | npt.NDArray[np.integer[Any]]) -> FitState:
        """The targets selected by the boolean or index array ``keep``."""
        return FitState(
            self.positions[keep],
            self.weights[keep],
            self.noise,
            self.heights[keep],
            self.log_gains[keep],
            self.log_scale,
        )

    def with_target(self, position: FloatArray, height: float) -> FitState:
        """This state plus one unit-gain target at ``position`` and ``height``."""
        return FitState(
            np.concatenate((self.positions, np.reshape(position, (1, 2)))),
            np.concatenate((self.weights, (1.0,))),
            self.noise,
            np.concatenate((self.heights, (height,))),
            np.concatenate((self.log_gains, (0.0,))),
            self.log_scale,
        )

    def reordered(self, order: npt.NDArray[np.integer[Any]]) -> FitState:
        """The targets in the order ``order``."""
        return self.subset(order)


@functools.lru_cache(maxsize=64)
def compiled_indices(model: Model, n_leds: int) -> tuple[IntArray, IntArray, FloatArray]:
    """:func:`_vech_indices` as the compiled kernels take them (writable int64 copies)."""
    upper, lower, is_diag = _vech_indices(model, n_leds)
    return (
        np.array(upper, dtype=np.int64),
        np.array(lower, dtype=np.int64),
        np.array(is_diag, dtype=np.float64),
    )


def fixed_tuple(kernel: ChannelKernel, state: FitState) -> tuple[Any, ...]:
    """The compiled kernels' ``fixed`` tuple of a state (no parameters in theta)."""
    heights = np.ascontiguousarray(state.heights, dtype=np.float64)
    facts = state.facts  # as Objective._state_facts: the same kernel's plane
    if facts is None:
        unit = (
            state.log_scale == 0.0
            and not state.log_gains.any()
            and bool((state.weights == 1.0).all())
        )
        facts = state.facts = (bool((heights == kernel.receiver_height).all()), bool(unit))
    return (
        heights,
        np.ascontiguousarray(state.weights, dtype=np.float64),
        np.ascontiguousarray(state.log_gains, dtype=np.float64),
        float(state.log_scale),
        facts[0],
        facts[1],
    )


@functools.lru_cache(maxsize=64)
def _vech_indices(model: Model, n_leds: int) -> tuple[IntArray, IntArray, FloatArray]:
    """Row and column of each measurement entry and its diagonal indicator (read-only)."""
    if model == "correlation":
        upper, lower = np.triu_indices(n_leds)
    else:
        upper = lower = np.arange(n_leds)
    is_diag = (upper == lower).astype(np.float64)
    for array in (upper, lower, is_diag):
        array.setflags(write=False)
    return upper, lower, is_diag


def entry_variances(
    sigma2: float, lam: FloatArray, upper: IntArray, lower: IntArray, is_diag: FloatArray
) -> FloatArray:
    """Noise variance of each entry of ``vech(U^T E U)``: ``sigma^2 (lam_a + lam_b)`` off the
    diagonal, ``4 sigma^2 lam_a`` on it (see :class:`Whitening`), shape (L,).

    Weighting each entry by ``1 / sqrt`` of it is the Gaussian (generalised least-squares)
    metric, and within a block of equal eigenvalues it is that block's Frobenius norm, so
    the metric does not depend on which eigenbasis the eigen-solver returns there.
    """
    return np.asarray(sigma2 * (lam[upper] + lam[lower]) * (1.0 + is_diag))


class Whitening:
    """Fixed linear whitening ``r -> c * vech(U^T E U)`` (correlation) or ``c * e`` (power).

    The aggregated noise of ``R = sum_k (g_k + n_k)(g_k + n_k)^T`` with i.i.d.
    ``n ~ N(0, sigma^2 I)`` has, for any symmetric test matrix ``A``,
    ``Var <A, R> = 4 sigma^2 tr(A M0 A)`` with ``M0 = S + K sigma^2 / 2 I`` and
    ``S = sum_k g_k g_k^T``. In the eigenbasis ``M0 = U diag(lam) U^T`` the entries of
    ``U^T E U`` are uncorrelated with variance ``sigma^2 (lam_a + lam_b)`` (``A`` the
    symmetrised unit pair) and ``4 sigma^2 lam_a`` on the diagonal (:func:`entry_variances`),
    and ``c`` is one over their square roots. For power the
    entries are independent with variance ``4 sigma^2 (S_ii + K sigma^2 / 2)``. The noise
    atom ``vech(I)`` is unchanged by the rotation (``U^T I U = I``).
    """

    def __init__(
        self, model: Model, n_leds: int, rotation: FloatArray | None, weights: FloatArray
    ) -> None:
        self.model = model
        self.n_leds = n_leds
        self.rotation = rotation
        self.rotation_t = None if rotation is None else np.ascontiguousarray(rotation.T)
        self.weights = weights
        self.upper, self.lower, self.is_diag = _vech_indices(model, n_leds)
        self.weighted_diag = weights * self.is_diag
        self._compiled: tuple[Any, ...] | None = None
        self._data: tuple[FloatArray, str, FloatArray] | None = None

    def compiled(self) -> tuple[Any, ...]:
        """This whitening as the compiled kernels take it (built once)."""
        if self._compiled is None:
            upper, lower, _ = compiled_indices(self.model, self.n_leds)
            # Without a rotation the kernels never read it: empty, not an M x M identity.
            rotation = np.zeros((0, 0)) if self.rotation is None else self.rotation
            self._compiled = (
                self.rotation is not None,
                np.ascontiguousarray(rotation, dtype=np.float64),
                np.ascontiguousarray(self.weights, dtype=np.float64),
                upper,
                lower,
                np.ascontiguousarray(self.weighted_diag, dtype=np.float64),
            )
        return self._compiled

    @classmethod
    def identity(cls, model: Model, n_leds: int) -> Whitening:
        """Plain least squares."""
        length = n_leds * (n_leds + 1) // 2 if model == "correlation" else n_leds
        return cls(model, n_leds, None, np.ones(length))

    @classmethod
    def from_state(
        cls, model: Model, kernel: ChannelKernel, state: FitState, n_terminals: float
    ) -> Whitening:
        """Plug-in whitening from the current fit (sigma^2 = s / K)."""
        constants = channel_constants(kernel) if kernel_mode() == "compiled" else None
        if constants is not None and state.n_targets > 0:
            upper, lower, is_diag = compiled_indices(model, kernel.n_leds)
            rotation, weights = whitening_kernel(
                *constants,
                np.ascontiguousarray(state.positions, dtype=np.float64),
                fixed_tuple(kernel, state),
                float(state.noise),
                float(n_terminals),
                model == "correlation",
                upper,
                lower,
                is_diag,
            )
            return cls(model, kernel.n_leds, rotation if model == "correlation" else None, weights)
        return cls._from_state_reference(model, kernel, state, n_terminals)

    @classmethod
    def _from_state_reference(
        cls, model: Model, kernel: ChannelKernel, state: FitState, n_terminals: float
    ) -> Whitening:
        """:meth:`from_state` in plain NumPy (the compiled kernel's reference)."""
        gains = target_gains(kernel, state)
        weights = state.effective_weights()
        # Floor sigma^2 at a fraction of the mean received power per LED and terminal: a
        # near-zero noise estimate would make the metric singular off the fitted signal.
        power = float(np.sum(gains**2 * weights)) / (kernel.n_leds * max(n_terminals, 1.0))
        sigma2 = max(state.noise / max(n_terminals, 1.0), _SIGMA2_REL_FLOOR * power, SIGMA2_FLOOR)
        half_noise = 0.5 * max(n_terminals, 1.0) * sigma2
        if model == "power":
            var = 4.0 * sigma2 * ((gains**2) @ weights + half_noise)
            return cls(model, kernel.n_leds, None, 1.0 / np.sqrt(var))
        signal = (gains * weights) @ gains.T
        signal.flat[:: kernel.n_leds + 1] += half_noise
        lam, rot = np.linalg.eigh(signal)
        lam = np.maximum(lam, EIG_FLOOR * max(float(lam[-1]), SIGMA2_FLOOR))
        upper, lower, is_diag = _vech_indices(model, kernel.n_leds)
        weights = 1.0 / np.sqrt(entry_variances(sigma2, lam, upper, lower, is_diag))
        return cls(model, kernel.n_leds, rot, weights)

    def data(self, values: FloatArray) -> FloatArray:
        """Whitened measurement. The last one is kept (a solve whitens its measurement in
        one metric many times): callers must not write into it (nor into ``values``). Not
        flagged read-only: the compiled kernels take writable arrays."""
        last = self._data
        if last is not None and last[0] is values and last[1] == kernel_mode():
            return last[2]
        whitened = self._data_of(values)
        if whitened.shape[0] <= _KEPT_DATA_MAX:  # a large room's whitening keeps none
            self._data = (values, kernel_mode(), whitened)
        return whitened

    def _data_of(self, values: FloatArray) -> FloatArray:
        if kernel_mode() == "compiled":
            return np.asarray(
                whiten_kernel(self.compiled(), np.ascontiguousarray(values, dtype=np.float64))
            )
        if self.rotation is None or self.rotation_t is None:
            return np.asarray(self.weights * values)
        full = np.zeros((self.n_leds, self.n_leds))
        full[self.upper, self.lower] = values
        full[self.lower, self.upper] = values
        rotated = self.rotation_t @ full @ self.rotation
        return np.asarray(self.weights * rotated[self.upper, self.lower])

    def rotate(self, vectors: FloatArray) -> FloatArray:
        """``U^T V`` for V of shape (M, n)."""
        if self.rotation_t is None:
            return vectors
        return np.asarray(self.rotation_t @ vectors)


def target_gains(kernel: ChannelKernel, state: FitState) -> FloatArray:
    """``g`` of every target of a state (at its height), shape (M, K)."""
    xs, ys = state.positions[:, 0], state.positions[:, 1]
    if np.all(state.heights == kernel.receiver_height):
        return kernel.gains_xy(xs, ys)
    return kernel.gains_xyz(xs, ys, state.heights)


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
        self._problem: tuple[Any, ...] | bool | None = False

    def compiled_problem(self) -> tuple[Any, ...] | None:
        """``(channel, table, white, data)`` for the compiled kernels; None when the
        reference kernels are in use (or the channel has no compiled form)."""
        if kernel_mode() != "compiled":
            return None
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
        slots = self.slots(fixed.n_targets)
        on_plane, unit = self._state_facts(fixed)
        priors = self.priors
        return (
            (
                np.ascontiguousarray(fixed.heights, dtype=np.float64),
                np.ascontiguousarray(fixed.weights, dtype=np.float64),
                np.ascontiguousarray(fixed.log_gains, dtype=np.float64),
                float(fixed.log_scale),
                on_plane,
                unit,
            ),
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

    def slots(self, n_targets: int) -> _Slots:
        """The parameter layout for K targets."""
        found = self._slots.get(n_targets)
        if found is None:
            found = self._slots[n_targets] = _Slots.make(n_targets, self.priors, self.free_weights)
        return found

    def pack(self, state: FitState) -> FloatArray:
        """``theta`` of a state."""
        slots = self.slots(state.n_targets)
        parts = [state.positions[:, 0], state.positions[:, 1]]
        if slots.n_axes == 3:
            parts.append(state.heights)
        if slots.weights is not None:
            parts.append(state.weights)
        if slots.gains is not None:
            parts.append(state.log_gains)
        if slots.scale is not None:
            parts.append(np.array([state.log_scale]))
        parts.append(np.array([state.noise]))
        return np.concatenate(parts)

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
        return FitState(positions, weights, float(theta[-1]), heights, log_gains, log_scale)

    def _state_facts(self, fixed: FitState) -> tuple[bool, bool]:
        """Whether ``fixed`` has every target on the receivers' plane, and unit multipliers
        (remembered on the state: LM evaluates many thetas against one)."""
        facts = fixed.facts
        if facts is None:
            on_plane = bool((fixed.heights == self.kernel.receiver_height).all())
            unit = (
                fixed.log_scale == 0.0
                and not fixed.log_gains.any()
                and bool((fixed.weights == 1.0).all())
            )
            facts = fixed.facts = (on_plane, unit)
        return facts

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
        problem = self.compiled_problem()
        if problem is not None and fixed.n_targets > 0:
            return np.asarray(
                residual_kernel(
                    *problem,
                    np.ascontiguousarray(theta, dtype=np.float64),
                    *self.compiled_state(fixed),
                )
            )
        return self.residual_reference(theta, fixed)

    def residual_reference(self, theta: FloatArray, fixed: FitState) -> FloatArray:
        """:meth:`residual` in plain NumPy (the compiled kernel's reference)."""
        white = self.white
        slots = self.slots(fixed.n_targets)
        k = slots.n_targets
        xs, ys = theta[:k], theta[k : 2 * k]
        if slots.n_axes == 3:
            gains = self.kernel.gains_xyz(xs, ys, theta[2 * k : 3 * k])
        elif self._state_facts(fixed)[0]:
            gains = self.kernel.gains_xy(xs, ys)
        else:
            gains = self.kernel.gains_xyz(xs, ys, fixed.heights)
        gains = white.rotate(gains)
        atoms = gains[white.upper] * gains[white.lower]
        multipliers = self._multipliers(theta, slots, fixed)
        model = atoms.sum(axis=1) if multipliers is None else atoms @ multipliers
        model *= white.weights
        residual = self.data - model
        residual -= theta[-1] * white.weighted_diag
        return np.concatenate((residual, self.prior_residuals(theta, slots)))

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


def levenberg_marquardt(
    objective: Objective,
    state: FitState,
    *,
    max_iter: int,
    initial_damping: float,
    tol: float,
    step_tol_m: float = STEP_TOL_M,
) -> tuple[FitState, float, int]:
    """Projected LM on an :class:`Objective` (parameters kept within their bounds).

    Every trial computes residual and Jacobian together: most steps are accepted, and a
    second call for the Jacobian would cost more than the wasted one on a rejection.

    Returns the refined state, its cost and the number of iterations used.
    """
    n_targets = state.n_targets
    lower, upper = objective.bounds(n_targets)
    theta = objective.pack(state)
    if objective.noise_ceiling < math.inf:
        # The state's noise may be above this objective's ceiling: start within the bounds.
        theta = np.clip(theta, lower, upper)
    problem = objective.compiled_problem()
    if problem is not None and n_targets > 0:
        theta, cost, used = lm_kernel(
            *problem,
            theta,
            *objective.compiled_state(state),
            lower,
            upper,
            int(max_iter),
            float(initial_damping),
            float(tol),
            float(step_tol_m),
        )
        return objective.unpack(theta, state), float(cost), int(used)
    normal, gradient, cost = gram(objective, theta, state)
    damping = initial_damping
    used = 0
    n_pos = 2 * n_targets
    converged = False
    while used < max_iter and not converged:
        used += 1
        scaling = np.diag(np.maximum(normal.diagonal(), DIAGONAL_FLOOR))
        for _ in range(MAX_REJECTIONS):
            _, step, info = lapack.dposv(normal + damping * scaling, gradient)
            if info != 0:
                damping *= DAMPING_SINGULAR
                continue
            # Converged when the step no longer moves any target or the linearised model
            # promises (almost) no decrease; the step is still tried.
            predicted = float(step @ (2.0 * gradient - normal @ step))
            converged = (
                n_pos == 0 or float(np.abs(step[:n_pos]).max()) < step_tol_m
            ) or predicted < tol * cost
            trial = np.clip(theta + step, lower, upper)
            trial_normal, trial_gradient, trial_cost = gram(objective, trial, state)
            if trial_cost < cost:
                converged = converged or (cost - trial_cost) < tol * cost
                theta, normal, gradient, cost = trial, trial_normal, trial_gradient, trial_cost
                damping = max(damping / DAMPING_DOWN, MIN_DAMPING)
                break
            if converged:
                break
            damping *= DAMPING_UP
        else:
            converged = True  # no decrease found along any damping: a local minimum
    return objective.unpack(theta, state), cost, used


def gram(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[FloatArray, FloatArray, float]:
    """``J^T J``, ``J^T r`` and ``r^T r`` at ``theta`` (one BLAS call instead of three)."""
    problem = objective.compiled_problem()
    if problem is not None and fixed.n_targets > 0:
        normal, gradient, cost = gram_kernel(
            *problem,
            np.ascontiguousarray(theta, dtype=np.float64),
            *objective.compiled_state(fixed),
        )
        return normal, gradient, float(cost)
    return gram_reference(objective, theta, fixed)


def gram_reference(
    objective: Objective, theta: FloatArray, fixed: FitState
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`gram` in plain NumPy (the compiled kernel's reference)."""
    augmented = objective.augmented(theta, fixed)
    product = augmented @ augmented.T
    n_params = theta.shape[0]
    return (
        product[:n_params, :n_params],
        product[:n_params, n_params],
        float(product[n_params, n_params]),
    )
