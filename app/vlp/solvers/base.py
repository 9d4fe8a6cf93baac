"""The one interface every localization solver shares.

A solver is built once per (fingerprint, model) -- that is where it may precompute
(normalised dictionaries, compiled convex programs) -- and then solves many measurements::

    solver = make_solver("gridless", fingerprint, "correlation")
    solution = solver.solve(measurement, n_targets=8)

The web layer caches solver objects per (room, fingerprint version, model, solver name).
A solver that can also locate each terminal from its own amplitudes says so by having
:meth:`TerminalSolver.solve_terminals`; the service asks for that protocol, not for a class.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

from ..constants import MAX_TARGETS
from ..errors import MeasurementError, SolverError, UnknownSolverError
from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
from ..radii import confidence_radii
from ..scale import check_measurement_scale
from ..typing import FloatArray, IntArray
from ..uncertainty import FitQuality

__all__ = [
    "MAX_TARGETS",
    "SOLVERS",
    "Solution",
    "Solver",
    "TerminalSolver",
    "make_solver",
    "register_solver",
    "solver_names",
    "with_radii",
]


@dataclass(frozen=True)
class Solution:
    """What a solver found.

    Attributes
    ----------
    positions : ndarray of shape (K, 2)
        Estimated ``(x, y)``, metres: grid centres for grid solvers, refined for gridless.
    grid_indices : ndarray of shape (K,)
        Nearest grid column of each estimate.
    weights : ndarray of shape (K,)
        Fitted occupancy of each estimate (about 1 for one terminal).
    noise_power : float
        Fitted coefficient of the noise atom (sigma^2), squared amplitude units.
    residual_norm : float
        Euclidean norm of the measurement minus the model's prediction.
    n_iter : int
        Iterations the solver used.
    converged : bool
        False when the solver stopped on an iteration limit.
    covariances : ndarray of shape (K, 2, 2) or None, m^2
        Covariance of each estimate's ``(x, y)`` (solvers that fit continuously).
    gains : ndarray of shape (K,) or None
        Each target's fitted amplitude gain relative to the fingerprint (1 = as modelled).
    heights : ndarray of shape (K,) or None, metres
        Each target's height, when heights were fitted or given.
    fit : FitQuality or None
        Goodness of the fit and the measurement's fitted scale.
    radii : ndarray of shape (K,) or None, metres
        Each estimate's 95 % radius (:func:`app.vlp.radii.confidence_radii` of
        ``covariances``); set whenever the covariances are, by the solver's ``_solve`` or
        else by :meth:`Solver.solve` (:func:`with_radii`).
    """

    positions: FloatArray
    grid_indices: IntArray
    weights: FloatArray
    noise_power: float
    residual_norm: float
    n_iter: int
    converged: bool
    covariances: FloatArray | None = None
    gains: FloatArray | None = None
    heights: FloatArray | None = None
    fit: FitQuality | None = None
    radii: FloatArray | None = None

    @property
    def n_targets(self) -> int:
        """K, the number of estimates."""
        return int(self.positions.shape[0])


def with_radii(solution: Solution) -> Solution:
    """``solution`` with the 95 % radii of its covariances (part of the answer a solve
    gives, so timed with it); unchanged without covariances or with radii already set."""
    if solution.covariances is None or solution.radii is not None:
        return solution
    return replace(solution, radii=confidence_radii(solution.covariances))


class Solver(ABC):
    """Base class: subclasses set ``name`` and implement :meth:`_solve`.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}
    """

    name: ClassVar[str]
    description: ClassVar[str] = ""

    def __init__(self, fingerprint: Fingerprint, model: Model) -> None:
        self.fingerprint = fingerprint
        self.model = model

    def solve(self, measurement: Measurement, n_targets: int | None = None) -> Solution:
        """Locate the targets behind one measurement.

        Parameters
        ----------
        measurement : Measurement
            Of this solver's model and the fingerprint's M.
        n_targets : int, default=None
            K; estimated from the measurement when None.

        Raises
        ------
        MeasurementError
            When the measurement's model or size does not match.
        SolverError
            When ``n_targets`` is out of range.
        """
        if measurement.model != self.model:
            raise MeasurementError(
                f"solver prepared for model {self.model!r} got a {measurement.model!r} measurement",
                field="model",
            )
        if measurement.n_leds != self.fingerprint.n_leds:
            raise MeasurementError(
                f"measurement is for {measurement.n_leds} LEDs, the room has "
                f"{self.fingerprint.n_leds}",
                field=measurement.model,
            )
        if n_targets is not None:
            limit = min(MAX_TARGETS, self.fingerprint.n_cells)
            if not 1 <= n_targets <= limit:
                raise SolverError(
                    f"targets must be between 1 and {limit}, got {n_targets}", field="targets"
                )
        check_measurement_scale(self.fingerprint, measurement, n_targets)
        solution = self._solve(measurement, n_targets)
        if not (
            np.isfinite(solution.positions).all()
            and np.isfinite(solution.weights).all()
            and math.isfinite(solution.noise_power)
            and math.isfinite(solution.residual_norm)
        ):
            # An answer of NaN or infinity is no answer; the measurement's scale is far
            # outside what this room's fingerprint can produce.
            raise SolverError(
                f"the measurement (largest value {np.max(np.abs(measurement.values)):.3g}) "
                "does not fit this room's fingerprint: the fit is not finite",
                field=measurement.model,
            )
        return with_radii(solution)

    @abstractmethod
    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        """Solve a validated measurement."""


@runtime_checkable
class TerminalSolver(Protocol):
    """A solver that also locates each terminal from its own pilot amplitudes (the labels
    are known: estimate k belongs to terminal k), which is more information than their sum.
    """

    def solve_terminals(
        self,
        amplitudes: FloatArray,
        heights: FloatArray | None = None,
        normals: FloatArray | None = None,
        floors: FloatArray | None = None,
    ) -> Solution:
        """Locate each terminal from its own amplitudes.

        Parameters
        ----------
        amplitudes : ndarray of shape (K, M)
            Each terminal's received pilot amplitudes (validated by the caller); NaN where
            the LED was not detected.
        heights : ndarray of shape (K,) or None, metres
            Terminals' own heights; NaN (or None for all) where unknown.
        normals : ndarray of shape (K, 3) or None
            Terminals' photodiode unit normals; None for straight up.
        floors : ndarray of shape (K,) or None
            Terminals' detection floors (amplitude units); NaN (or None for all) where not
            sent.
        """
        ...


SOLVERS: dict[str, type[Solver]] = {}


def register_solver(cls: type[Solver]) -> type[Solver]:
    """Class decorator adding a solver to :data:`SOLVERS` under ``cls.name``."""
    SOLVERS[cls.name] = cls
    return cls


def solver_names() -> list[str]:
    """Registered solver names, the default first."""
    return sorted(SOLVERS, key=lambda name: (name != "gridless", name))


def make_solver(name: str, fingerprint: Fingerprint, model: Model) -> Solver:
    """Build the solver registered as ``name`` for a fingerprint and model.

    Raises
    ------
    UnknownSolverError
        When no solver has that name.
    """
    try:
        cls = SOLVERS[name]
    except KeyError:
        raise UnknownSolverError(
            f"unknown solver {name!r}; choose one of {solver_names()}", field="solver"
        ) from None
    return cls(fingerprint, model)
