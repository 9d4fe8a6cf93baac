"""Localization solvers behind one interface (see :mod:`app.vlp.solvers.base`)."""

from . import gridless, l1, nnls, omp  # noqa: F401  (imported to register the solvers)
from ._warm_up import warm_up
from .base import (
    MAX_TARGETS,
    SOLVERS,
    Solution,
    Solver,
    TerminalSolver,
    make_solver,
    register_solver,
    solver_names,
)

__all__ = [
    "MAX_TARGETS",
    "SOLVERS",
    "Solution",
    "Solver",
    "TerminalSolver",
    "make_solver",
    "register_solver",
    "solver_names",
    "warm_up",
]
