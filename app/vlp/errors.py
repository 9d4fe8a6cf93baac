"""Errors raised by the science core.

The tree::

    VLPError                      anything the science core refuses or cannot do
    ├── GeometryError             a room layout that is not physically valid
    ├── MeasurementError          a measurement of the wrong shape, sign or value
    ├── ProblemSizeError          a problem larger than a configured limit
    └── SolverError               a solver that cannot run on the given problem
        ├── UnknownSolverError    a solver name that is not registered
        └── SolverFailed          the solver ran on a valid problem and found no answer
                                  (e.g. l1 did not converge): not the input's fault

Each error carries ``field`` (a dotted path such as ``"leds[3].z"`` or ``"correlation"``)
when one input is to blame, so the web layer can name it in a problem detail.
"""

from __future__ import annotations

__all__ = [
    "GeometryError",
    "MeasurementError",
    "ProblemSizeError",
    "SolverError",
    "SolverFailed",
    "UnknownSolverError",
    "VLPError",
]


class VLPError(ValueError):
    """Base class of every error the science core raises on bad input."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


class GeometryError(VLPError):
    """A room layout that is not physically valid (sizes, grid, LEDs, angles)."""


class MeasurementError(VLPError):
    """A measurement vector or matrix of the wrong shape, sign or value."""


class ProblemSizeError(VLPError):
    """A problem larger than a configured limit (grid points, LEDs, dense matrices)."""


class SolverError(VLPError):
    """A solver that cannot run on the given problem (e.g. more targets than grid points)."""


class UnknownSolverError(SolverError):
    """A solver name that is not registered."""


class SolverFailed(SolverError):
    """A valid problem on which the solver found no answer (a numerical failure, such as a
    convex program that did not converge); the web layer answers it as a server-side
    problem, not as invalid input."""
