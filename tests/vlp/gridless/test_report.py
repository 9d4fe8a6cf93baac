"""The aggregated forms' profiles (gridless.report.profiles) against residuals formed
one estimate at a time, and what they do to an answer's radii."""

from __future__ import annotations

import numpy as np
import pytest

from app.vlp._kernels import KernelMode, use_kernels
from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import Model, measurement_from_amplitudes
from app.vlp.simulation import Impairments, random_positions, simulate_terminals
from app.vlp.solvers.gridless import fitting
from app.vlp.solvers.gridless.fitting import (
    Run,
    fits_to_noise,
    grid_correlations,
    noise_test,
    residual_of,
    whitening_of,
)
from app.vlp.solvers.gridless.report import profiles
from app.vlp.solvers.gridless.room import PreparedRoom
from app.vlp.solvers.gridless.solver import GridlessSolver
from app.vlp.solvers.gridless.state import FitState
from app.vlp.solvers.gridless.whitening import Whitening


@pytest.mark.parametrize("model", ["correlation", "power"])
def test_profiles_equal_the_insertion_fit_of_each_estimate_s_own_residual(
    paper_fingerprint: Fingerprint, model: Model
) -> None:
    layout = paper_fingerprint.layout
    rng = np.random.default_rng(7)
    solver, run, truth = _simulated_run(paper_fingerprint, model, 4, rng)
    # Off the truth, other heights, gains and scale: every term of the model in play.
    state = FitState(
        truth + rng.normal(0.0, 0.05, truth.shape),
        np.ones(4),
        0.02,
        layout.grid.receiver_height + rng.normal(0.0, 0.05, 4),
        rng.normal(0.0, 0.1, 4),
        0.05,
    )
    explained, best = profiles(solver.room, run, state)

    white = whitening_of(solver.room, state)
    full = residual_of(solver.room, run, white, state)
    atoms = _whitened_atoms(solver, white)
    norms = np.einsum("jl,jl->j", atoms, atoms)
    for k in range(4):
        others = residual_of(solver.room, run, white, state.subset(np.arange(4) != k))
        expected = np.maximum(atoms @ others, 0.0) ** 2 / norms
        np.testing.assert_allclose(explained[k], expected, rtol=1e-9, atol=1e-9 * expected.max())
        own = float(others @ others - full @ full)
        assert best[k] == pytest.approx(max(expected.max(), own), rel=1e-9)


@pytest.mark.parametrize("mode", ["reference", "compiled"])
@pytest.mark.parametrize("model", ["correlation", "power"])
def test_insertion_scores_are_the_inner_products_of_atoms_whitened_one_by_one(
    paper_fingerprint: Fingerprint, model: Model, mode: KernelMode
) -> None:
    """``<c psi_j, r>`` and ``||c psi_j||^2`` of the grid scan against each grid point's
    atom whitened on its own (the whitened diagonal counts once, as in the fit's cost)."""
    layout = paper_fingerprint.layout
    solver, run, truth = _simulated_run(paper_fingerprint, model, 3, np.random.default_rng(12))
    state = FitState(
        truth[:2], np.ones(2), 0.02, np.full(2, layout.grid.receiver_height), np.zeros(2), 0.0
    )
    white = whitening_of(solver.room, state)
    residual = residual_of(solver.room, run, white, state)
    with use_kernels("reference"):
        atoms = _whitened_atoms(solver, white)
    with use_kernels(mode):
        num, norms = grid_correlations(solver.room, white, residual)
    np.testing.assert_allclose(num, atoms @ residual, rtol=1e-9, atol=1e-12 * np.abs(num).max())
    np.testing.assert_allclose(norms, np.einsum("jl,jl->j", atoms, atoms), rtol=1e-9)


def _simulated_run(
    fingerprint: Fingerprint, model: Model, k: int, rng: np.random.Generator
) -> tuple[GridlessSolver, Run, np.ndarray]:
    """A solver, the run of an ideal 30 dB measurement of ``k`` random targets, the truth."""
    layout = fingerprint.layout
    truth = random_positions(layout, k, rng=rng)
    simulated = simulate_terminals(layout, truth, Impairments.ideal(), snr_db=30.0, rng=rng)
    measurement = measurement_from_amplitudes(simulated.amplitudes, model, layout.n_leds)
    solver = GridlessSolver(fingerprint, model)
    return (
        solver,
        Run(values=measurement.values / solver.room.scale**2, priors=solver.room.priors),
        truth,
    )


def _whitened_atoms(solver: GridlessSolver, white: Whitening) -> np.ndarray:
    """Every grid point's atom (``vech(g g^T)`` or ``g o g``) whitened on its own, (N, L)."""
    gains = solver.room.gains
    if solver.model == "correlation":
        upper, lower = np.triu_indices(gains.shape[0])
        unwhitened = gains[upper] * gains[lower]
    else:
        unwhitened = gains**2
    return np.array([white.data(unwhitened[:, j].copy()) for j in range(gains.shape[1])])


def test_a_state_is_whitened_and_its_residual_formed_once_per_run(
    paper_fingerprint: Fingerprint, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The escape tests and the profiles of one state share one whitened residual per run
    (gridless.fitting.whitened_residual), equal to the one formed anew; another state, or
    another run of the same values, forms its own."""
    layout = paper_fingerprint.layout
    rng = np.random.default_rng(3)
    solver, run, truth = _simulated_run(paper_fingerprint, "correlation", 3, rng)
    state = FitState(
        truth + rng.normal(0.0, 0.03, truth.shape),
        np.ones(3),
        0.02,
        np.full(3, layout.grid.receiver_height),
        np.zeros(3),
        0.0,
    )
    want = residual_of(solver.room, run, whitening_of(solver.room, state), state)
    formed: list[int] = []
    original = fitting.residual_of

    def counted(room: PreparedRoom, run: Run, white: Whitening, state: FitState) -> np.ndarray:
        formed.append(state.n_targets)
        return original(room, run, white, state)

    monkeypatch.setattr(fitting, "residual_of", counted)
    first = noise_test(solver.room, run, state)
    assert noise_test(solver.room, run, state)[1] is first[1]
    assert fits_to_noise(solver.room, run, state) == first[2]
    profiles(solver.room, run, state)
    assert len(formed) == 1
    np.testing.assert_array_equal(first[1], want)
    moved = FitState(
        state.positions + 0.01, state.weights, state.noise, state.heights, state.log_gains, 0.0
    )
    noise_test(solver.room, run, moved)
    noise_test(solver.room, Run(values=run.values, priors=run.priors), state)
    assert len(formed) == 3
