"""What the service asks a solver for: the base interface, and locating each terminal from
its own amplitudes (:class:`~app.vlp.solvers.TerminalSolver`), asked by protocol."""

from __future__ import annotations

import numpy as np

from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers import TerminalSolver, make_solver, solver_names


def test_the_default_solver_alone_fits_each_terminal(paper_fingerprint: Fingerprint) -> None:
    kinds = {
        name: isinstance(make_solver(name, paper_fingerprint, "correlation"), TerminalSolver)
        for name in solver_names()
    }
    assert kinds == {name: name == "gridless" for name in solver_names()}


def test_estimate_k_is_terminal_k(paper_fingerprint: Fingerprint) -> None:
    solver = make_solver("gridless", paper_fingerprint, "correlation")
    assert isinstance(solver, TerminalSolver)
    truth = np.array([[3.7, 0.8], [0.9, 3.1], [2.2, 2.4]])
    solution = solver.solve_terminals(true_amplitudes(paper_fingerprint.layout, truth))
    # Noiseless amplitudes: each estimate on its own terminal, in the order they were sent.
    np.testing.assert_allclose(solution.positions, truth, atol=1e-3)


def test_every_answer_with_covariances_carries_their_radii(
    paper_fingerprint: Fingerprint,
) -> None:
    # The radii are part of what a solve returns (timed with it), for both ways of solving.
    solver = make_solver("gridless", paper_fingerprint, "correlation")
    assert isinstance(solver, TerminalSolver)
    truth = np.array([[3.7, 0.8], [0.9, 3.1]])
    amplitudes = true_amplitudes(paper_fingerprint.layout, truth)
    noisy = amplitudes * (1.0 + 0.01 * np.random.default_rng(2).standard_normal(amplitudes.shape))
    measured = measurement_from_amplitudes(noisy, "correlation", paper_fingerprint.n_leds)
    for solution in (solver.solve(measured, 2), solver.solve_terminals(noisy)):
        assert solution.covariances is not None and solution.radii is not None
        # an isotropic covariance s^2 I holds 95 % within s sqrt(-2 ln 0.05); in general the
        # radius lies between that of the smaller and of the larger eigenvalue
        eigenvalues = np.linalg.eigvalsh(solution.covariances)
        scale = np.sqrt(-2.0 * np.log(0.05))
        assert np.all(solution.radii >= scale * np.sqrt(eigenvalues[:, 0]) - 1e-12)
        assert np.all(solution.radii <= scale * np.sqrt(eigenvalues[:, 1]) + 1e-12)
    # a solver without covariances gives no radii
    grid = make_solver("omp", paper_fingerprint, "correlation").solve(measured, 2)
    assert grid.covariances is None and grid.radii is None
