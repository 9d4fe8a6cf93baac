"""The plug-in whitening of the aggregated measurements (docs/explanation/solver.md,
"Whitening"): the entries' indices, their variances under a state, the whitening itself and
the targets' gains it is computed from.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from ..._kernels import dispatch, kernel_mode
from ...measurements import Model
from ...typing import FloatArray, IntArray
from ._compiled import fit as compiled_fit
from ._compiled.channel import channel_constants
from .channel import ChannelKernel
from .lm import (
    EIG_FLOOR,
    SIGMA2_FLOOR,
    SIGMA2_REL_FLOOR,
)
from .state import FitState

# Whitened measurements of at most this many values are kept by their Whitening.
_KEPT_DATA_MAX = 4096


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
    facts = state.facts_on(kernel.receiver_height)
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
        self.weights = weights
        self.upper, self.lower, self.is_diag = _vech_indices(model, n_leds)
        self.weighted_diag = weights * self.is_diag
        self._compiled: tuple[Any, ...] | None = None
        self._data: tuple[FloatArray, str, FloatArray] | None = None
        # Unit weights and no rotation (:meth:`identity`): the data are the values.
        self._plain = False

    @functools.cached_property
    def rotation_t(self) -> FloatArray | None:
        """``U^T``, contiguous, for the NumPy rotations (made when first asked for: the
        compiled kernels read ``U``); None without a rotation."""
        return None if self.rotation is None else np.ascontiguousarray(self.rotation.T)

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
        white = cls(model, n_leds, None, np.ones(length))
        white._plain = True
        return white

    @classmethod
    def from_state(
        cls, model: Model, kernel: ChannelKernel, state: FitState, n_terminals: float
    ) -> Whitening:
        """Plug-in whitening from the current fit (sigma^2 = s / K)."""
        return dispatch(whitening_kernel, whitening_reference)(model, kernel, state, n_terminals)

    def data(self, values: FloatArray) -> FloatArray:
        """Whitened measurement. The last one is kept (a solve whitens its measurement in
        one metric many times): callers must not write into it (nor into ``values``). Not
        flagged read-only: the compiled kernels take writable arrays. In plain least squares,
        the values themselves (what either kernel gives: each times 1)."""
        if self._plain:
            return np.asarray(values, dtype=np.float64)
        last = self._data
        if last is not None and last[0] is values and last[1] == kernel_mode():
            return last[2]
        whitened = self._data_of(values)
        if whitened.shape[0] <= _KEPT_DATA_MAX:  # a large room's whitening keeps none
            self._data = (values, kernel_mode(), whitened)
        return whitened

    def keep(self, values: FloatArray, whitened: FloatArray) -> None:
        """Keep ``whitened``, computed elsewhere by the kernels in use (a compiled step that
        whitened ``values`` on its way), as :meth:`data` of ``values``."""
        if not self._plain and whitened.shape[0] <= _KEPT_DATA_MAX:
            self._data = (values, kernel_mode(), whitened)

    def _data_of(self, values: FloatArray) -> FloatArray:
        return dispatch(whitened_data_kernel, whitened_data_reference)(self, values)

    def rotate(self, vectors: FloatArray) -> FloatArray:
        """``U^T V`` for V of shape (M, n)."""
        if self.rotation_t is None:
            return vectors
        return np.asarray(self.rotation_t @ vectors)


def whitening_kernel(
    model: Model, kernel: ChannelKernel, state: FitState, n_terminals: float
) -> Whitening:
    """:func:`whitening_reference` in one compiled call (in NumPy without targets, or for a
    channel without a compiled form)."""
    constants = channel_constants(kernel)
    if constants is None or state.n_targets == 0:
        return whitening_reference(model, kernel, state, n_terminals)
    upper, lower, is_diag = compiled_indices(model, kernel.n_leds)
    rotation, weights = compiled_fit.whitening_kernel(
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
    return Whitening(model, kernel.n_leds, rotation if model == "correlation" else None, weights)


def whitening_reference(
    model: Model, kernel: ChannelKernel, state: FitState, n_terminals: float
) -> Whitening:
    """:meth:`Whitening.from_state` in plain NumPy."""
    gains = target_gains(kernel, state)
    weights = state.effective_weights()
    # Floor sigma^2 at a fraction of the mean received power per LED and terminal: a
    # near-zero noise estimate would make the metric singular off the fitted signal.
    power = float(np.sum(gains**2 * weights)) / (kernel.n_leds * max(n_terminals, 1.0))
    sigma2 = max(state.noise / max(n_terminals, 1.0), SIGMA2_REL_FLOOR * power, SIGMA2_FLOOR)
    half_noise = 0.5 * max(n_terminals, 1.0) * sigma2
    if model == "power":
        var = 4.0 * sigma2 * ((gains**2) @ weights + half_noise)
        return Whitening(model, kernel.n_leds, None, 1.0 / np.sqrt(var))
    signal = (gains * weights) @ gains.T
    signal.flat[:: kernel.n_leds + 1] += half_noise
    lam, rot = np.linalg.eigh(signal)
    lam = np.maximum(lam, EIG_FLOOR * max(float(lam[-1]), SIGMA2_FLOOR))
    upper, lower, is_diag = _vech_indices(model, kernel.n_leds)
    weights = 1.0 / np.sqrt(entry_variances(sigma2, lam, upper, lower, is_diag))
    return Whitening(model, kernel.n_leds, rot, weights)


def whitened_data_kernel(white: Whitening, values: FloatArray) -> FloatArray:
    """:func:`whitened_data_reference` in one compiled call."""
    return np.asarray(
        compiled_fit.whitened_data_kernel(
            white.compiled(), np.ascontiguousarray(values, dtype=np.float64)
        )
    )


def whitened_data_reference(white: Whitening, values: FloatArray) -> FloatArray:
    """The measurement ``values`` whitened by ``white``, in plain NumPy."""
    if white.rotation is None or white.rotation_t is None:
        return np.asarray(white.weights * values)
    full = np.zeros((white.n_leds, white.n_leds))
    full[white.upper, white.lower] = values
    full[white.lower, white.upper] = values
    rotated = white.rotation_t @ full @ white.rotation
    return np.asarray(white.weights * rotated[white.upper, white.lower])


def target_gains(kernel: ChannelKernel, state: FitState) -> FloatArray:
    """``g`` of every target of a state (at its height), shape (M, K)."""
    xs, ys = state.positions[:, 0], state.positions[:, 1]
    if (state.heights == kernel.receiver_height).all():
        return kernel.gains_xy(xs, ys)
    return kernel.gains_xyz(xs, ys, state.heights)
