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
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from .._typing import FloatArray, IntArray
from ..channel import led_constants
from ..layout import Layout
from ..measurements import Model

# Relative floor on whitening eigenvalues (guards a noiseless fit against infinite weights).
_EIG_FLOOR = 1e-9
# Smallest noise variance (normalised units) assumed when whitening, absolute and relative
# to the mean received power (1e-4: an SNR of 40 dB).
_SIGMA2_FLOOR = 1e-12
_SIGMA2_REL_FLOOR = 1e-4
# Damping increases tried per LM iteration before the point is taken as a local minimum.
_MAX_REJECTIONS = 12
# Marquardt damping factors after a rejected / accepted step (the start is the caller's).
# Nielsen's adaptive update needs a third fewer evaluations but lands in worse local
# minima on irregular rooms (measured: 12-LED irregular room, 40 dB, K=4 1.52 -> 3.79 cm).
_DAMPING_UP = 4.0
_DAMPING_DOWN = 5.0


class ChannelKernel:
    """Normalised scaled gains ``g(p) = x * h(p) / scale`` and their position gradients.

    Parameters
    ----------
    layout : Layout
    scale : float
        Divisor of the gains (see the module docstring).
    """

    def __init__(self, layout: Layout, scale: float) -> None:
        orders, prefactors = led_constants(layout)
        leds = layout.led_positions
        self.n_leds = layout.n_leds
        self.led_xy = np.ascontiguousarray(leds[:, :2])
        self.dz2 = (leds[:, 2] - layout.grid.receiver_height) ** 2
        self.orders = orders
        # h = pref * dz^(m+1) / d^(m+3); fold dz^(m+1), the pilot and 1/scale into one factor.
        dz = np.sqrt(self.dz2)
        self.factor = prefactors * dz ** (orders + 1.0) * layout.pilot_amplitudes / scale
        self.half_exponent = 0.5 * (orders + 3.0)
        # In view when dz / d >= cos(FOV), i.e. d^2 <= dz^2 / cos^2(FOV).
        cos_fov = math.cos(math.radians(layout.receiver.fov_deg))
        self.max_d2 = self.dz2 / max(cos_fov, 1e-300) ** 2 * (1.0 + 1e-12)
        self.bounds = np.array([layout.room.length, layout.room.width])
        # Column vectors (M, 1) for broadcasting against (M, P) in the hot path.
        self._led_x = self.led_xy[:, :1]
        self._led_y = self.led_xy[:, 1:]
        self._dz2 = self.dz2[:, None]
        self._factor = self.factor[:, None]
        self._minus_half_exponent = -self.half_exponent[:, None]
        self._minus_twice_half_exponent = -2.0 * self.half_exponent[:, None]
        self._max_d2 = self.max_d2[:, None]

    def stacked(self, points: FloatArray, with_gradients: bool) -> FloatArray:
        """Columns ``[g | dg/dx | dg/dy]`` of shape (M, 3P), or ``g`` alone (M, P)."""
        n_points = points.shape[0]
        if not with_gradients:
            return self.gains_xy(points[:, 0], points[:, 1])
        blocks = self.gradients_xy(points[:, 0], points[:, 1])
        return np.concatenate(
            [blocks[:, 2 * n_points : 3 * n_points], blocks[:, : 2 * n_points]], axis=1
        )

    def gains_xy(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """``g`` at the points ``(xs, ys)`` (shapes (P,)), shape (M, P)."""
        d2 = self._distances_squared(xs, ys)[2]
        gains = np.power(d2, self._minus_half_exponent)
        gains *= self._factor
        gains *= d2 <= self._max_d2
        return gains

    def gradients_xy(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """Columns ``[dg/dx | dg/dy | g | g]`` of shape (M, 4P) at the points ``(xs, ys)``.

        The order suits :meth:`Objective.augmented`: the gains twice, next to both gradient
        blocks, make the product rule one multiply per side.
        """
        n_points = xs.shape[0]
        out = np.empty((self.n_leds, 4 * n_points))
        gains = out[:, 2 * n_points : 3 * n_points]
        dx, dy, d2 = self._distances_squared(xs, ys)
        np.power(d2, self._minus_half_exponent, out=gains)
        gains *= self._factor
        gains *= d2 <= self._max_d2
        slope = self._minus_twice_half_exponent * gains
        slope /= d2
        np.multiply(slope, dx, out=out[:, :n_points])
        np.multiply(slope, dy, out=out[:, n_points : 2 * n_points])
        out[:, 3 * n_points :] = gains
        return out

    def _distances_squared(
        self, xs: FloatArray, ys: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        dx = xs - self._led_x
        dy = ys - self._led_y
        d2 = dx * dx
        d2 += dy * dy
        d2 += self._dz2
        return dx, dy, d2


@dataclass
class FitState:
    """Current estimate: positions (K, 2) m, weights (K,), noise coefficient s (normalised)."""

    positions: FloatArray
    weights: FloatArray
    noise: float

    @classmethod
    def empty(cls) -> FitState:
        """No targets yet."""
        return cls(np.zeros((0, 2)), np.zeros(0), 0.0)

    @property
    def n_targets(self) -> int:
        """K."""
        return int(self.positions.shape[0])


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


class Whitening:
    """Fixed linear whitening ``r -> c * vech(U^T E U)`` (correlation) or ``c * e`` (power).

    The aggregated noise of ``R = sum_k (g_k + n_k)(g_k + n_k)^T`` with i.i.d.
    ``n ~ N(0, sigma^2 I)`` has, for any symmetric test matrix ``A``,
    ``Var <A, R> = 4 sigma^2 tr(A M0 A)`` with ``M0 = S + K sigma^2 / 2 I`` and
    ``S = sum_k g_k g_k^T``. In the eigenbasis ``M0 = U diag(lam) U^T`` the entries of
    ``U^T E U`` are uncorrelated with variance ``2 sigma^2 (lam_a + lam_b)``
    (``4 sigma^2 lam_a`` on the diagonal), which gives the weights ``c``. For power the
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
        gains = kernel.stacked(state.positions, with_gradients=False)
        # Floor sigma^2 at a fraction of the mean received power per LED and terminal: a
        # near-zero noise estimate would make the metric singular off the fitted signal.
        power = float(np.sum(gains**2 * state.weights)) / (kernel.n_leds * max(n_terminals, 1.0))
        sigma2 = max(state.noise / max(n_terminals, 1.0), _SIGMA2_REL_FLOOR * power, _SIGMA2_FLOOR)
        half_noise = 0.5 * max(n_terminals, 1.0) * sigma2
        if model == "power":
            var = 4.0 * sigma2 * ((gains**2) @ state.weights + half_noise)
            return cls(model, kernel.n_leds, None, 1.0 / np.sqrt(var))
        signal = (gains * state.weights) @ gains.T
        signal.flat[:: kernel.n_leds + 1] += half_noise
        lam, rot = np.linalg.eigh(signal)
        lam = np.maximum(lam, _EIG_FLOOR * max(float(lam[-1]), _SIGMA2_FLOOR))
        upper, lower, is_diag = _vech_indices(model, kernel.n_leds)
        # Variance 2 sigma^2 (lam_a + lam_b), doubled on the diagonal; off-diagonal entries
        # count twice in the Frobenius norm, hence the factor 2 - is_diag.
        var = 2.0 * sigma2 * (lam[upper] + lam[lower]) * (1.0 + is_diag)
        weights = np.sqrt((2.0 - is_diag) / var)
        return cls(model, kernel.n_leds, rot, weights)

    def data(self, values: FloatArray) -> FloatArray:
        """Whitened measurement."""
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


class Objective:
    """``||data - c * mu(theta)||^2`` in one whitened metric, with its Jacobian.

    Parameters are packed as ``theta = [x_1..x_K, y_1..y_K, (w_1..w_K), s]``.

    Parameters
    ----------
    kernel : ChannelKernel
    white : Whitening
    values : ndarray of shape (L,)
        The measurement in normalised units (not yet whitened).
    free_weights : bool
    """

    def __init__(
        self, kernel: ChannelKernel, white: Whitening, values: FloatArray, free_weights: bool
    ) -> None:
        self.kernel = kernel
        self.white = white
        self.data = white.data(values)
        self.free_weights = free_weights

    def pack(self, state: FitState) -> FloatArray:
        """``theta`` of a state."""
        parts = [state.positions[:, 0], state.positions[:, 1]]
        if self.free_weights:
            parts.append(state.weights)
        parts.append(np.array([state.noise]))
        return np.concatenate(parts)

    def project(self, theta: FloatArray, upper: FloatArray) -> FloatArray:
        """Clip positions into the room and weights and noise to be nonnegative (in place);
        ``upper`` holds the room's length K times, then its width K times, then infinities."""
        return np.clip(theta, 0.0, upper, out=theta)

    def upper_bounds(self, n_targets: int) -> FloatArray:
        """The ``upper`` argument of :meth:`project`."""
        length, width = self.kernel.bounds
        n_rest = (n_targets if self.free_weights else 0) + 1
        return np.concatenate(
            [np.full(n_targets, length), np.full(n_targets, width), np.full(n_rest, np.inf)]
        )

    def unpack(self, theta: FloatArray, state: FitState) -> FitState:
        """State of ``theta`` (fixed weights taken from ``state``)."""
        k = state.n_targets
        positions = np.column_stack((theta[:k], theta[k : 2 * k]))
        weights = theta[2 * k : 3 * k].copy() if self.free_weights else state.weights
        return FitState(positions, weights, float(theta[-1]))

    def residual(self, theta: FloatArray, weights: FloatArray | None) -> FloatArray:
        """Whitened residual ``c * (y - mu(theta))``, shape (L,).

        Parameters
        ----------
        theta : ndarray of shape (2K + [K] + 1,)
        weights : ndarray of shape (K,) or None
            The fixed weights (ignored with free weights); None means all ones.
        """
        white = self.white
        k = self._n_targets(theta)
        if self.free_weights:
            weights = theta[2 * k : 3 * k]
        gains = white.rotate(self.kernel.gains_xy(theta[:k], theta[k : 2 * k]))
        atoms = gains[white.upper] * gains[white.lower]
        return self._residual(atoms, weights, theta[-1])

    def augmented(self, theta: FloatArray, weights: FloatArray | None) -> FloatArray:
        """``[J | r]^T`` of shape (len(theta) + 1, L): the Jacobian of ``c * mu`` and the
        residual as rows of one array, so that one product gives ``J^T J``, ``J^T r`` and
        ``r^T r``. Rows rather than columns: every product below then runs on contiguous
        memory, which is a third faster at these sizes than on strided column slices.
        """
        white = self.white
        k = self._n_targets(theta)
        if self.free_weights:
            weights = theta[2 * k : 3 * k]
        # Rows [dg/dx | dg/dy | g | g] (rotated: (U^T G)^T = G^T U); then the entries' a and b.
        blocks = self.kernel.gradients_xy(theta[:k], theta[k : 2 * k]).T
        if white.rotation is not None:
            blocks = blocks @ white.rotation
        left = blocks[:, white.upper]
        right = blocks[:, white.lower]
        atoms = left[2 * k : 3 * k] * right[2 * k : 3 * k]  # (K, L)
        n_params = theta.shape[0]
        augmented = np.empty((n_params + 1, atoms.shape[1]))
        model = atoms.sum(axis=0) if weights is None else weights @ atoms
        model *= white.weights
        residual = augmented[n_params]
        np.subtract(self.data, model, out=residual)
        residual -= theta[-1] * white.weighted_diag
        # d(g_a g_b)/dp = dg_a g_b + g_a dg_b, both axes at once: rows x_1..x_K, y_1..y_K.
        positions = augmented[: 2 * k]
        np.multiply(left[: 2 * k], right[2 * k :], out=positions)
        positions += left[2 * k :] * right[: 2 * k]
        if weights is not None:
            positions *= np.concatenate((weights, weights))[:, None]
        positions *= white.weights
        if self.free_weights:
            np.multiply(atoms, white.weights, out=augmented[2 * k : 3 * k])
        augmented[n_params - 1] = white.weighted_diag
        return augmented

    def _n_targets(self, theta: FloatArray) -> int:
        return int((theta.shape[0] - 1) // (3 if self.free_weights else 2))

    def _residual(self, atoms: FloatArray, weights: FloatArray | None, noise: float) -> FloatArray:
        model = atoms.sum(axis=1) if weights is None else atoms @ weights
        model *= self.white.weights
        residual = self.data - model
        residual -= noise * self.white.weighted_diag
        return residual

    def cost(self, state: FitState) -> tuple[float, FloatArray]:
        """Cost and whitened residual of a state."""
        residual = self.residual(self.pack(state), _fixed(state))
        return float(residual @ residual), residual


def _fixed(state: FitState) -> FloatArray | None:
    """The fixed weights to pass to :meth:`Objective.residual` (None when all are one)."""
    return None if bool(np.all(state.weights == 1.0)) else state.weights


def levenberg_marquardt(
    objective: Objective,
    state: FitState,
    *,
    max_iter: int,
    initial_damping: float,
    tol: float,
    step_tol_m: float = 1e-5,
) -> tuple[FitState, float, int]:
    """Projected LM on an :class:`Objective` (positions kept inside the room).

    Every trial computes residual and Jacobian together: most steps are accepted, and a
    second call for the Jacobian would cost more than the wasted one on a rejection.

    Returns the refined state, its cost and the number of iterations used.
    """
    n_targets = state.n_targets
    weights = _fixed(state)
    upper = objective.upper_bounds(n_targets)
    theta = objective.pack(state)
    normal, gradient, cost = _gram(objective, theta, weights)
    damping = initial_damping
    used = 0
    n_pos = 2 * n_targets
    converged = False
    while used < max_iter and not converged:
        used += 1
        scaling = np.diag(np.maximum(normal.diagonal(), 1e-30))
        for _ in range(_MAX_REJECTIONS):
            _, step, info = lapack.dposv(normal + damping * scaling, gradient)
            if info != 0:
                damping *= 10.0
                continue
            # Converged when the step no longer moves any target or the linearised model
            # promises (almost) no decrease; the step is still tried.
            predicted = float(step @ (2.0 * gradient - normal @ step))
            converged = (
                n_pos == 0 or float(np.abs(step[:n_pos]).max()) < step_tol_m
            ) or predicted < tol * cost
            trial = objective.project(theta + step, upper)
            trial_normal, trial_gradient, trial_cost = _gram(objective, trial, weights)
            if trial_cost < cost:
                converged = converged or (cost - trial_cost) < tol * cost
                theta, normal, gradient, cost = trial, trial_normal, trial_gradient, trial_cost
                damping = max(damping / _DAMPING_DOWN, 1e-9)
                break
            if converged:
                break
            damping *= _DAMPING_UP
        else:
            converged = True  # no decrease found along any damping: a local minimum
    return objective.unpack(theta, state), cost, used


def _gram(
    objective: Objective, theta: FloatArray, weights: FloatArray | None
) -> tuple[FloatArray, FloatArray, float]:
    """``J^T J``, ``J^T r`` and ``r^T r`` at ``theta`` (one BLAS call instead of three)."""
    augmented = objective.augmented(theta, weights)
    gram = augmented @ augmented.T
    n_params = theta.shape[0]
    return gram[:n_params, :n_params], gram[:n_params, n_params], float(gram[n_params, n_params])
