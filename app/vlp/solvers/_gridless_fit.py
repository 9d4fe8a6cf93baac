"""Continuous model and whitened Levenberg-Marquardt fit behind the ``gridless`` solver.

Everything here works in *normalised* units: gains are divided by ``scale``, the root of
the mean of ``(h_ij x_i)^2`` over LEDs and grid points (the SNR convention's signal
power), so a measurement ``y`` is divided by ``scale^2`` and a noise variance in these units
is ``10^(-SNR/10)``. The model of one measurement with targets at ``p_k`` is

.. math::

    \\mu(\\theta) = \\sum_k w_k \\phi(g(p_k)) + s\\, a, \\qquad
    \\phi(g) = \\mathrm{vech}(g g^T) \\text{ (correlation) or } g \\circ g \\text{ (power)},

with ``a`` the noise atom (``vech(I)`` or ones). Private: callers validate.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

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
# Marquardt damping: start, and the factors after a rejected / accepted step. Nielsen's
# adaptive update needs a third fewer evaluations but lands in worse local minima on
# irregular rooms (measured: 12-LED irregular room, 40 dB, K=4 1.52 -> 3.79 cm).
_INITIAL_DAMPING = 1e-3
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
        dx = points[:, 0] - self._led_x
        dy = points[:, 1] - self._led_y
        d2 = dx * dx + dy * dy + self._dz2
        gains = self._factor * d2**self._minus_half_exponent
        gains *= d2 <= self._max_d2
        if not with_gradients:
            return np.asarray(gains)
        slope = self._minus_twice_half_exponent * gains / d2
        return np.concatenate([gains, slope * dx, slope * dy], axis=1)


@dataclass
class FitState:
    """Current estimate: positions (K, 2) m, weights (K,), noise coefficient s (normalised)."""

    positions: FloatArray
    weights: FloatArray
    noise: float


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
    entries are independent with variance ``4 sigma^2 (S_ii + K sigma^2 / 2)``.
    """

    def __init__(
        self, model: Model, n_leds: int, rotation: FloatArray | None, weights: FloatArray
    ) -> None:
        self.model = model
        self.rotation = rotation
        self.weights = weights
        self.upper, self.lower, self.is_diag = _vech_indices(model, n_leds)

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
        lam, rot = np.linalg.eigh(signal + half_noise * np.eye(kernel.n_leds))
        lam = np.maximum(lam, _EIG_FLOOR * max(float(lam[-1]), _SIGMA2_FLOOR))
        upper, lower, is_diag = _vech_indices(model, kernel.n_leds)
        # Variance 2 sigma^2 (lam_a + lam_b), doubled on the diagonal; off-diagonal entries
        # count twice in the Frobenius norm, hence the factor 2 - is_diag.
        var = 2.0 * sigma2 * (lam[upper] + lam[lower]) * (1.0 + is_diag)
        weights = np.sqrt((2.0 - is_diag) / var)
        return cls(model, kernel.n_leds, rot, weights)

    def data(self, values: FloatArray, n_leds: int) -> FloatArray:
        """Whitened measurement."""
        if self.model == "power" or self.rotation is None:
            return np.asarray(self.weights * values)
        full = np.zeros((n_leds, n_leds))
        full[self.upper, self.lower] = values
        full = full + np.triu(full, 1).T
        rotated = self.rotation.T @ full @ self.rotation
        return np.asarray(self.weights * rotated[self.upper, self.lower])

    def rotate(self, vectors: FloatArray) -> FloatArray:
        """``U^T V`` for V of shape (M, n)."""
        if self.rotation is None:
            return vectors
        return np.asarray(self.rotation.T @ vectors)


def residual_and_jacobian(
    kernel: ChannelKernel,
    white: Whitening,
    data: FloatArray,
    state: FitState,
    free_weights: bool,
    want_jacobian: bool = True,
) -> tuple[FloatArray, FloatArray | None]:
    """Whitened residual ``c * (y - mu)`` and its Jacobian wrt (positions, [weights], s).

    Returns
    -------
    residual : ndarray of shape (L,)
    jacobian : ndarray of shape (L, 2K + [K] + 1) or None
        Derivative of the *model* term ``c * mu`` (so a Gauss-Newton step solves
        ``J delta = residual``).
    """
    k = state.positions.shape[0]
    w = state.weights
    c = white.weights
    # One rotation for gains and both gradient components: columns [g | dg/dx | dg/dy].
    stacked = white.rotate(kernel.stacked(state.positions, want_jacobian))
    left = stacked[white.upper]
    right = stacked[white.lower]
    atoms = left[:, :k] * right[:, :k]  # (L, K)
    residual = data - c * (atoms @ w + state.noise * white.is_diag)
    if not want_jacobian:
        return residual, None
    n_rows = len(c)
    jac = np.empty((n_rows, 2 * k + (k if free_weights else 0) + 1))
    # d(g_a g_b)/dp = g_a dg_b + dg_a g_b for both axes at once, as (L, axis, K); the
    # columns are ordered (x_1, y_1, x_2, y_2, ...).
    d_left = left[:, k:].reshape(n_rows, 2, k)
    d_right = right[:, k:].reshape(n_rows, 2, k)
    both = w * (left[:, None, :k] * d_right + d_left * right[:, None, :k])
    jac[:, : 2 * k] = both.transpose(0, 2, 1).reshape(n_rows, 2 * k)
    if free_weights:
        jac[:, 2 * k : 3 * k] = atoms
    jac[:, -1] = white.is_diag
    jac *= c[:, None]
    return residual, jac


def _pack(state: FitState, free_weights: bool) -> FloatArray:
    parts = [state.positions.ravel()]
    if free_weights:
        parts.append(state.weights)
    parts.append(np.array([state.noise]))
    return np.concatenate(parts)


def _unpack(theta: FloatArray, state: FitState, free_weights: bool, bounds: FloatArray) -> FitState:
    k = state.positions.shape[0]
    positions = np.clip(theta[: 2 * k].reshape(k, 2), 0.0, bounds)
    weights = np.maximum(theta[2 * k : 3 * k], 0.0) if free_weights else state.weights
    return FitState(positions, weights, max(float(theta[-1]), 0.0))


def levenberg_marquardt(
    kernel: ChannelKernel,
    white: Whitening,
    data: FloatArray,
    state: FitState,
    *,
    free_weights: bool,
    max_iter: int,
    tol: float = 1e-7,
    step_tol_m: float = 1e-5,
) -> tuple[FitState, float, int]:
    """Projected LM on ``||data - c * mu(theta)||^2`` (positions kept inside the room).

    Returns the refined state, its cost and the number of iterations used.
    """
    residual, jac = residual_and_jacobian(kernel, white, data, state, free_weights)
    cost = float(residual @ residual)
    damping = _INITIAL_DAMPING
    used = 0
    theta = _pack(state, free_weights)
    n_pos = state.positions.size
    converged = False
    while used < max_iter and not converged:
        used += 1
        assert jac is not None
        normal = jac.T @ jac
        gradient = jac.T @ residual
        scaling = np.diag(np.maximum(np.diag(normal), 1e-30))
        for _ in range(_MAX_REJECTIONS):
            try:
                step = np.linalg.solve(normal + damping * scaling, gradient)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            # Converged when the step no longer moves any target or the linearised model
            # promises (almost) no decrease; the step is still tried.
            predicted = float(step @ (2.0 * gradient - normal @ step))
            converged = (
                float(np.max(np.abs(step[:n_pos]), initial=0.0)) < step_tol_m
                or predicted < tol * cost
            )
            trial = _unpack(theta + step, state, free_weights, kernel.bounds)
            trial_res, _ = residual_and_jacobian(
                kernel, white, data, trial, free_weights, want_jacobian=False
            )
            trial_cost = float(trial_res @ trial_res)
            if trial_cost < cost:
                converged = converged or (cost - trial_cost) < tol * cost
                state, cost = trial, trial_cost
                if not converged:
                    residual, jac = residual_and_jacobian(kernel, white, data, state, free_weights)
                theta = _pack(state, free_weights)
                damping = max(damping / _DAMPING_DOWN, 1e-9)
                break
            if converged:
                break
            damping *= _DAMPING_UP
        else:
            converged = True  # no decrease found along any damping: a local minimum
    return state, cost, used
