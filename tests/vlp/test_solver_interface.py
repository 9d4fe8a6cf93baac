"""What the service asks a solver for: the base interface, and locating each terminal from
its own amplitudes (:class:`~app.vlp.solvers.TerminalSolver`), asked by protocol."""

from __future__ import annotations

import numpy as np

from app.vlp.fingerprints import Fingerprint
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
