"""Whitenings and whitened data kept between the steps of a solve (``gridless.whitening_memo``)."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np

from app.vlp._kernels import KERNELS, use_kernels
from app.vlp.fingerprints import build_fingerprint
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.solvers.gridless.fitting import plug_in_whitening, whitening_of
from app.vlp.solvers.gridless.state import FitState
from app.vlp.solvers.gridless.whitening import Whitening
from app.vlp.solvers.gridless.whitening_memo import MAX_KEPT_VALUES, WhiteningMemo


def _state() -> FitState:
    return FitState(
        np.array([[1.0, 1.2], [2.5, 3.0]]), np.ones(2), 1e-3, np.full(2, 0.85), np.zeros(2)
    )


def test_a_whitening_is_reused_only_for_the_same_values() -> None:
    solver = GridlessSolver(build_fingerprint(paper_layout()), "correlation")
    state = _state()
    first = whitening_of(solver.room, state)
    # Another object with the same values: the same whitening, which is the one computed.
    # (``facts`` describe the values they were computed from: a changed copy starts without.)
    assert whitening_of(solver.room, dataclasses.replace(state, facts=None)) is first
    fresh = plug_in_whitening(solver.room, state)
    np.testing.assert_array_equal(first.weights, fresh.weights)
    assert first.rotation is not None and fresh.rotation is not None
    np.testing.assert_array_equal(first.rotation, fresh.rotation)
    # Any value changed: computed afresh.
    for changed in (
        dataclasses.replace(state, noise=2e-3, facts=None),
        dataclasses.replace(
            state, positions=state.positions + np.array([[1e-9, 0.0], [0, 0]]), facts=None
        ),
        dataclasses.replace(state, log_gains=np.array([0.0, 0.1]), facts=None),
        dataclasses.replace(state, log_scale=0.1, facts=None),
        dataclasses.replace(state, heights=np.array([0.85, 0.9]), facts=None),
        dataclasses.replace(state, weights=np.array([1.0, 2.0]), facts=None),
    ):
        assert whitening_of(solver.room, changed) is not first
    # The kernels in use are part of the key (their eigenbases may differ).
    with use_kernels("reference"):
        assert whitening_of(solver.room, state) is not first
    # Each thread keeps its own.
    other: list[Whitening] = []
    thread = threading.Thread(target=lambda: other.append(whitening_of(solver.room, state)))
    thread.start()
    thread.join()
    assert other[0] is not first


def test_the_memo_is_bounded() -> None:
    memo = WhiteningMemo()
    calls = []

    def compute(state: FitState) -> Whitening:
        calls.append(state.noise)
        return Whitening.identity("power", 16)

    for i in range(200):
        memo.get(dataclasses.replace(_state(), noise=float(i)), compute)
    assert len(calls) == 200
    assert len(memo._local.known) <= 64


def test_large_whitenings_are_not_kept() -> None:
    """A large room's whitening (an M x M rotation, M(M+1)/2 weights) is computed afresh
    rather than held by every thread."""
    memo = WhiteningMemo()
    size = MAX_KEPT_VALUES + 1
    big = [Whitening("power", size, None, np.full(size, 2.0)) for _ in range(2)]
    calls = iter(big)
    state = _state()
    assert memo.get(state, lambda _: next(calls)) is big[0]
    assert memo.get(state, lambda _: next(calls)) is big[1]
    values = np.ones(size)
    assert big[0].data(values) is not big[0].data(values)
    np.testing.assert_array_equal(big[0].data(values), 2.0 * values)


def test_plain_least_squares_whitens_nothing() -> None:
    """The plain metric's data are the values themselves, as either kernel computes them
    (each times 1), without a copy."""
    values = np.random.default_rng(3).normal(size=136)
    plain = Whitening.identity("correlation", 16)
    assert plain.data(values) is values
    for kernels in KERNELS:
        with use_kernels(kernels):
            np.testing.assert_array_equal(plain._data_of(values), values)


def test_whitened_data_is_kept_for_the_same_array() -> None:
    solver = GridlessSolver(build_fingerprint(paper_layout()), "correlation")
    white = whitening_of(solver.room, _state())
    values = np.linspace(0.0, 1.0, white.weights.shape[0])
    first = white.data(values)
    assert white.data(values) is first
    again = white.data(values.copy())  # equal values, another array: computed again
    assert again is not first
    np.testing.assert_array_equal(again, first)


def test_answers_do_not_depend_on_what_the_memo_holds() -> None:
    """Solving the same measurements in another order (other whitenings kept) and with a
    fresh solver gives the same answers, bit for bit."""
    layout = paper_layout()
    fingerprint = build_fingerprint(layout)
    std = noise_std_for_snr(fingerprint, 30.0)
    measurements = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        truth = random_positions(layout, 3, rng=rng)
        amplitudes = noisy_amplitudes(layout, truth, std, rng=rng)
        measurements.append(measurement_from_amplitudes(amplitudes, "correlation", 16))
    shared = GridlessSolver(fingerprint, "correlation")
    forward = [shared.solve(m, 3) for m in measurements]
    backward = [shared.solve(m, 3) for m in reversed(measurements)][::-1]
    for m, a, b in zip(measurements, forward, backward, strict=True):
        c = GridlessSolver(fingerprint, "correlation").solve(m, 3)
        for got in (b, c):
            np.testing.assert_array_equal(got.positions, a.positions)
            assert got.covariances is not None and a.covariances is not None
            np.testing.assert_array_equal(got.covariances, a.covariances)
