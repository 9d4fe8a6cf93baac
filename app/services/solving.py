"""Solving a read measurement: its work bounded, its solve timed, its answer labelled.

A :class:`Task` is a validated measurement of one room version (made by
:mod:`app.services.localization` from a request body, or from an epoch's terminals);
:func:`check_work` refuses one that asks for too much before any of it is done,
:func:`solve_task` solves it on the version's prepared solver and :func:`label_solution` makes the
answer, each estimate labelled with its terminal when the terminals' own amplitudes are
known.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import TypeAdapter

from app.schemas import Estimate, Fit, Localization
from app.telemetry import Metrics
from app.vlp.assignment import assign_terminals
from app.vlp.errors import ProblemSizeError
from app.vlp.measurements import Measurement, Model
from app.vlp.typing import FloatArray
from app.vlp.workload import LocalizeWork, localize_work

from .fingerprint_cache import PreparedVersion

if TYPE_CHECKING:
    from app.vlp.solvers import Solution, Solver, TerminalSolver

__all__ = [
    "Solved",
    "Task",
    "TerminalSet",
    "check_work",
    "fits_each_terminal",
    "label_solution",
    "solve_and_label",
    "solve_task",
    "task_work",
    "work_from_counts",
]


# An answer's estimates, validated in one call (K model constructions cost several times more).
_ESTIMATES = TypeAdapter(list[Estimate])


@dataclass(frozen=True)
class TerminalSet:
    """Terminals' own amplitudes: ``amplitudes[k]`` (M numbers) were sent by ``ids[k]``;
    ``heights[k]`` (NaN: unknown) and ``normals[k]`` (unit vectors) when they sent them."""

    ids: tuple[str, ...]
    amplitudes: FloatArray
    heights: FloatArray | None = None
    normals: FloatArray | None = None
    # NaN amplitudes: LEDs not detected; floors[k] the terminal's own floor (NaN: not sent).
    floors: FloatArray | None = None

    @property
    def filled(self) -> FloatArray:
        """The amplitudes with each undetected LED at half its terminal's floor (for the
        aggregated forms, which cannot say "not detected")."""
        from app.vlp.solvers._censored import censored_substitutes  # see _terminal_solver

        return censored_substitutes(self.amplitudes, self.floors)[0]


@dataclass(frozen=True)
class Task:
    """What to solve: a validated measurement on (room, version) with the named solver."""

    room_id: str
    version: int
    measurement: Measurement
    solver: str
    targets: int | None
    terminals: TerminalSet | None
    form: str  # the body's field that carried the measurement


def _terminal_solver(solver: Solver) -> TerminalSolver | None:
    """``solver`` when it also fits each terminal from its own amplitudes, else None.

    The solvers are imported where they are used, not with this module: an API process
    imports them (and numba) when it first prepares a solver
    (:class:`app.services.fingerprint_cache.FingerprintCache`), and one that never solves
    does not hold them. Here they are already imported: a prepared solver exists.
    """
    from app.vlp.solvers import TerminalSolver

    return solver if isinstance(solver, TerminalSolver) else None


def _per_terminal(prepared: PreparedVersion, task: Task) -> bool:
    """Whether each terminal is fitted from its own amplitudes (labels known, not guessed)."""
    n_terminals = None if task.terminals is None else len(task.terminals.ids)
    return fits_each_terminal(prepared, n_terminals, task.targets)


def fits_each_terminal(
    prepared: PreparedVersion, n_terminals: int | None, targets: int | None
) -> bool:
    """:func:`_per_terminal` from the counts: ``n_terminals`` sent (None: no terminals) and
    the ``targets`` asked for."""
    return (
        n_terminals is not None
        and _terminal_solver(prepared.solver) is not None
        and targets in (None, n_terminals)
    )


def task_work(prepared: PreparedVersion, task: Task) -> LocalizeWork:
    """The work a solve of ``task`` asks for (:func:`app.vlp.workload.localize_work`)."""
    n_terminals = None if task.terminals is None else len(task.terminals.ids)
    return work_from_counts(prepared, task.measurement.model, n_terminals, task.targets)


def work_from_counts(
    prepared: PreparedVersion, model: Model, n_terminals: int | None, targets: int | None
) -> LocalizeWork:
    """:func:`task_work` from the counts (as :func:`fits_each_terminal`) and the model."""
    fingerprint = prepared.fingerprint
    per_terminal = fits_each_terminal(prepared, n_terminals, targets)
    if targets is None and n_terminals is not None:
        targets = n_terminals
    return localize_work(
        n_cells=fingerprint.n_cells,
        n_leds=fingerprint.n_leds,
        model=model,
        targets=targets,
        terminals=n_terminals if per_terminal else None,
    )


def check_work(prepared: PreparedVersion, task: Task, max_work: int) -> None:
    """Refuse, before any of it is done, a solve that asks for more than ``max_work``
    (:func:`app.vlp.workload.localize_work`; the service's ``VLP_MAX_LOCALIZE_WORK``).

    Raises
    ------
    ProblemSizeError
        Naming ``terminals`` when each terminal is fitted on its own, else ``targets``, or
        the measurement's own field when even one target would be too much.
    """
    fingerprint = prepared.fingerprint
    per_terminal = _per_terminal(prepared, task)
    model = task.measurement.model
    work = task_work(prepared, task)
    if work.units <= max_work:
        return
    one = localize_work(
        n_cells=fingerprint.n_cells, n_leds=fingerprint.n_leds, model=model, targets=1
    )
    if per_terminal:
        field, advice = "terminals", "send fewer terminals per request"
    elif one.units <= max_work:
        field, advice = "targets", "send a smaller targets"
    else:
        field = task.form
        advice = (
            "send the power vector or the terminals' own amplitudes instead"
            if model == "correlation"
            else "this room is too large for this model and solver"
        )
    raise ProblemSizeError(
        f"this request asks for {work.describe()} units of work, more than this server's "
        f"limit {max_work} (VLP_MAX_LOCALIZE_WORK); {advice}",
        field=field,
    )


def solve_and_label(
    prepared: PreparedVersion, metrics: Metrics, task: Task, *, lock_held: bool = False
) -> Localization:
    """Solve an aggregated measurement and, when the terminals' own amplitudes are known,
    label each estimate with its terminal (per-terminal fit, else an assignment problem).
    The solve holds ``prepared.lock`` (a solver solves one measurement at a time), unless
    the caller already does (``lock_held``)."""
    solved = solve_task(prepared, metrics, task, lock_held=lock_held)
    return label_solution(prepared, task, solved)


@dataclass(frozen=True)
class Solved:
    """A task's solution and the solver's time on it (seconds)."""

    solution: Solution
    elapsed_s: float


def solve_task(
    prepared: PreparedVersion, metrics: Metrics, task: Task, *, lock_held: bool = False
) -> Solved:
    """The solve of :func:`solve_and_label`, timed (the answer's ``elapsed_ms``)."""
    measurement, terminals, targets = task.measurement, task.terminals, task.targets
    if terminals is not None and targets is None:
        targets = len(terminals.ids)  # the contract: one target per terminal sent
    # Only terminals ask which kind the solver is: the check against a runtime protocol
    # costs more than the rest of an answer's labelling.
    own = None if terminals is None else _terminal_solver(prepared.solver)
    per_terminal = _per_terminal(prepared, task)
    with contextlib.nullcontext() if lock_held else prepared.lock:
        started = time.perf_counter()
        if per_terminal and terminals is not None and own is not None:
            solution = own.solve_terminals(
                terminals.amplitudes, terminals.heights, terminals.normals, terminals.floors
            )
        else:
            solution = prepared.solver.solve(measurement, targets)
        elapsed = time.perf_counter() - started
    metrics.localize_latency.labels(solver=task.solver, model=measurement.model).observe(elapsed)
    return Solved(solution, elapsed)


def label_solution(prepared: PreparedVersion, task: Task, solved: Solved) -> Localization:
    """The answer of :func:`solve_and_label`: the solution, each estimate labelled with
    its terminal when the terminals' own amplitudes are known."""
    solution, terminals = solved.solution, task.terminals
    owners: list[str | None] = [None] * solution.n_targets
    if terminals is not None and _per_terminal(prepared, task):
        owners = list(terminals.ids)
    elif terminals is not None:
        assigned = assign_terminals(
            prepared.fingerprint.layout, solution.positions, terminals.filled
        )
        owners = [terminals.ids[int(index)] if index >= 0 else None for index in assigned]
    return Localization(
        room_id=task.room_id,
        fingerprint_version=task.version,
        model=task.measurement.model,
        solver=task.solver,
        targets=solution.n_targets,
        estimates=_estimates(solution, owners),
        residual_norm=float(solution.residual_norm),
        noise_power=float(solution.noise_power),
        elapsed_ms=round(solved.elapsed_s * 1e3, 3),
        converged=bool(solution.converged),
        # read off the fit's attributes: dataclasses.asdict deep-copies every field first
        fit=None
        if solution.fit is None
        else Fit.model_validate(solution.fit, from_attributes=True),
    )


def _estimates(solution: Solution, owners: list[str | None]) -> list[Estimate]:
    """The answer's estimates, with their uncertainty, gain and height when the solver
    gives them: each array read out once (``tolist``: Python floats and ints, the values
    ``float()``/``int()`` give one by one) and the K estimates validated in one call."""
    n_targets = solution.n_targets
    missing: list[None] = [None] * n_targets

    def column(values: FloatArray | None) -> list[Any]:
        return missing if values is None else list(values.tolist())

    rows = zip(
        solution.positions.tolist(),
        solution.grid_indices.tolist(),
        solution.weights.tolist(),
        owners,
        column(solution.radii),
        column(solution.covariances),
        column(solution.gains),
        column(solution.heights),
        strict=True,
    )
    return _ESTIMATES.validate_python(
        [
            {
                "x": position[0],
                "y": position[1],
                "grid_index": grid_index,
                "weight": weight,
                "terminal_id": owner,
                "accuracy_m": radius,
                "covariance": covariance,
                "gain": gain,
                "z": height,
            }
            for position, grid_index, weight, owner, radius, covariance, gain, height in rows
        ]
    )
