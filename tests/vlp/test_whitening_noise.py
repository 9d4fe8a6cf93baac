"""The correlation whitening against the noise it whitens: simulated aggregated correlations
``R = sum_k (g_k + n_k)(g_k + n_k)^T`` give whitened entries of unit variance, on the diagonal
as off it, and the metric does not depend on the eigenbasis of repeated eigenvalues."""

from __future__ import annotations

import numpy as np
import pytest

from app.vlp._kernels import KernelMode, use_kernels
from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import mean_signal_power
from app.vlp.solvers.gridless.channel import ChannelKernel
from app.vlp.solvers.gridless.state import FitState
from app.vlp.solvers.gridless.whitening import (
    Whitening,
    target_gains,
)

N_DRAWS = 4000


def _state(kernel: ChannelKernel, noise: float) -> FitState:
    positions = np.array([[1.1, 1.3], [3.2, 2.4], [2.0, 3.9]])
    k = positions.shape[0]
    return FitState(
        positions, np.ones(k), noise, np.full(k, kernel.receiver_height), np.zeros(k), 0.0
    )


def _kernel() -> ChannelKernel:
    """The paper room's line-of-sight channel at the solver's scale (gains of order one)."""
    fingerprint = build_fingerprint(paper_layout())
    return ChannelKernel(fingerprint.layout, float(np.sqrt(mean_signal_power(fingerprint))), None)


@pytest.mark.parametrize("mode", ["reference", "compiled"])
def test_whitened_noise_has_unit_variance_on_and_off_the_diagonal(mode: KernelMode) -> None:
    kernel = _kernel()
    probe = _state(kernel, 0.0)
    gains = target_gains(kernel, probe).T  # (K, M)
    k, n_leds = gains.shape
    sigma = 0.05 * float(np.sqrt(np.mean(gains**2)))
    state = _state(kernel, k * sigma**2)  # the fit's noise coefficient is K sigma^2
    with use_kernels(mode):
        white = Whitening.from_state("correlation", kernel, state, float(k))
    rng = np.random.default_rng(5)
    upper, lower = np.triu_indices(n_leds)
    expected = gains.T @ gains + k * sigma**2 * np.eye(n_leds)
    whitened = np.empty((N_DRAWS, upper.shape[0]))
    for draw in range(N_DRAWS):
        received = gains + sigma * rng.standard_normal((k, n_leds))
        correlation = received.T @ received - expected
        with use_kernels(mode):
            whitened[draw] = white._data_of(correlation[upper, lower])
    variances = whitened.var(axis=0)
    diagonal = upper == lower
    # 4000 draws: a variance's relative standard error is sqrt(2 / 4000) = 2.2 %.
    assert np.median(variances[diagonal]) == pytest.approx(1.0, abs=0.04)
    assert np.median(variances[~diagonal]) == pytest.approx(1.0, abs=0.04)
    assert np.all(np.abs(variances - 1.0) < 0.15)


def test_the_metric_does_not_depend_on_the_basis_of_the_unlit_directions() -> None:
    """The M - K directions the targets do not light share one eigenvalue; any orthonormal
    basis of them is the eigen-solver's to choose, so the whitened norm must not change."""
    kernel = _kernel()
    state = _state(kernel, 3e-3)
    with use_kernels("reference"):
        white = Whitening.from_state("correlation", kernel, state, 3.0)
    assert white.rotation is not None
    n_leds = white.n_leds
    rng = np.random.default_rng(9)
    spin, _ = np.linalg.qr(rng.standard_normal((n_leds - 3, n_leds - 3)))
    rotation = white.rotation.copy()
    rotation[:, : n_leds - 3] = rotation[:, : n_leds - 3] @ spin  # eigh sorts them first
    other = Whitening("correlation", n_leds, rotation, white.weights)
    n_entries = n_leds * (n_leds + 1) // 2
    for _ in range(5):
        values = rng.standard_normal(n_entries)
        with use_kernels("reference"):
            norms = [float(np.linalg.norm(w._data_of(values))) for w in (white, other)]
        assert norms[1] == pytest.approx(norms[0], rel=1e-9)
