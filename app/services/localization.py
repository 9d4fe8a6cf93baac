"""Localization: one measurement against one room version, the targets' positions out.

Entry points:

- :func:`localize_measurement`: a localize request body (``app.schemas.Measurement``) against
  the room's current or pinned version. ``POST /v1/rooms/{id}/localize`` calls it; so does any
  other router that localizes a request body (one call per measurement).
- :class:`RoomLocalizer`: the same for many bodies of one room (a batch's items), each read,
  solved and answered in steps of its own, so that a batch can take each step for all of
  its items in turn; :func:`localize_measurement` is one of these, used once.
- :func:`localize_terminals`: terminals' amplitudes already held by the service (an epoch's
  posts, fitted to its fingerprint) against one version.

Both take one cache lookup (:meth:`FingerprintCache.prepare`: fingerprint, masked LEDs and
prepared solver together) and solve through :func:`_solve_and_label`, so they answer the
same way. Each input rule is checked once: the form and terminal ids and normals here, each
terminal's amplitude count in :mod:`app.services.masking`, shapes, signs and finiteness in
:mod:`app.vlp.measurements`, the target count in the solver.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import TypeAdapter

from app.errors import InvalidFields
from app.schemas import Estimate, Fit, Localization, Measurement, TerminalAmplitudes
from app.telemetry import Metrics
from app.vlp.assignment import assign_terminals
from app.vlp.errors import MeasurementError, ProblemSizeError
from app.vlp.measurements import Measurement as MeasurementVector
from app.vlp.measurements import (
    Model,
    measurement_from_amplitudes,
    measurement_from_correlation,
    measurement_from_power,
)
from app.vlp.typing import FloatArray
from app.vlp.workload import LocalizeWork, localize_work

from .fingerprint_cache import FingerprintCache, PreparedVersion
from .masking import drop_masked_leds

if TYPE_CHECKING:
    from app.vlp.solvers import Solution, Solver, TerminalSolver

__all__ = [
    "WAITLESS_TARGETS",
    "WAITLESS_WORK",
    "ReadMeasurement",
    "RoomLocalizer",
    "SolvedMeasurement",
    "TerminalSet",
    "censored_terminal_set",
    "check_work",
    "input_form",
    "localize_in_memory",
    "localize_measurement",
    "localize_terminals",
    "nothing_detected",
    "task_work",
]

_FORMS = ("power", "correlation", "terminals")
# The largest solve (localize_work units) that :func:`localize_in_memory` does where it is
# called, on the event loop, instead of in a worker thread: a room of the paper's size (400
# points, 16 LEDs, K = 8 correlation: 435 200 units) solves in a few milliseconds, about
# the interpreter's switch interval, for which a worker thread would hold the GIL as
# long; the hop to it and back costs two thread switches, which a loaded machine
# stretches. Larger solves go to a worker thread and leave the loop free. The work is a
# bound, not a prediction, and each target or terminal costs its own fits: more than
# WAITLESS_TARGETS of them (a crowd of terminals in a small room) go to the pool too.
WAITLESS_WORK = 1_000_000
WAITLESS_TARGETS = 8
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


def input_form(body: Measurement) -> tuple[str, Model]:
    """Which of ``power``/``correlation``/``terminals`` was sent, and the model it implies.

    Raises
    ------
    InvalidFields
        Unless exactly one was sent, or when ``model`` contradicts it.
    """
    sent = [form for form in _FORMS if getattr(body, form) is not None]
    if len(sent) != 1:
        names = sent or list(_FORMS)
        what = "none of them was" if not sent else f"{len(sent)} were"
        raise InvalidFields(
            [
                (form, f"send exactly one of power, correlation, terminals; {what} sent")
                for form in names
            ]
        )
    form = sent[0]
    if form == "terminals":
        return form, body.model
    implied: Model = "power" if form == "power" else "correlation"
    if "model" in body.model_fields_set and body.model != implied:
        raise InvalidFields(
            [
                (
                    "model",
                    f"model {body.model!r} does not fit `{form}`; "
                    f"use model {implied!r} or leave it out",
                )
            ]
        )
    return form, implied


def localize_measurement(
    cache: FingerprintCache,
    metrics: Metrics,
    *,
    room_id: str,
    body: Measurement,
    max_work: int | None = None,
) -> Localization:
    """Localize one request body against one version of the room (``body.fingerprint_version``,
    else the current one); ``max_work`` bounds the solve (:func:`check_work`).

    Raises
    ------
    InvalidFields, MeasurementError, SolverError
        A body that does not fit the room (each names its field).
    RoomNotFound, FingerprintNotReady, FingerprintNotFound, CorruptMatrix
    """
    return RoomLocalizer(cache, metrics, room_id=room_id, max_work=max_work).localize(body)


class RoomLocalizer:
    """Request bodies of one room localized as :func:`localize_measurement` localizes each
    (which is one of these, used once), in three steps a batch takes item by item: each
    body read (:meth:`read`: validated against the room, its measurement made and its work
    checked), each solved (:meth:`solve`), each answered (:meth:`answer`).

    A batch's items share one: the room's current version is read once, when an item first
    needs it (so every item sees the same one), and the prepared solver of each (version,
    model, solver) is looked up in the cache once.
    """

    def __init__(
        self,
        cache: FingerprintCache,
        metrics: Metrics,
        *,
        room_id: str,
        max_work: int | None = None,
    ) -> None:
        self._cache = cache
        self._metrics = metrics
        self._room_id = room_id
        self._max_work = max_work
        self._current: int | None = None
        self._prepared: dict[tuple[int, Model, str], PreparedVersion] = {}

    def localize(self, body: Measurement) -> Localization:
        """The body's localization (:func:`localize_measurement`, which says what it raises)."""
        return self.answer(self.solve(self.read(body)))

    def read(self, body: Measurement) -> ReadMeasurement:
        """The body as a measurement of its room version, ready to solve.

        Raises
        ------
        InvalidFields, MeasurementError, ProblemSizeError
            A body that does not fit the room (each names its field).
        RoomNotFound, FingerprintNotReady, FingerprintNotFound, CorruptMatrix
        """
        form, model = input_form(body)
        version = body.fingerprint_version
        if version is None:
            if self._current is None:
                self._current = self._cache.current_version(self._room_id)
            version = self._current
        key = (version, model, body.solver)
        prepared = self._prepared.get(key)
        if prepared is None:
            prepared = self._cache.prepare(self._room_id, version, model, body.solver)
            self._prepared[key] = prepared
        task = _measurement_task(prepared, self._room_id, version, body, form, model)
        if self._max_work is not None:
            check_work(prepared, task, self._max_work)
        return ReadMeasurement(prepared, task)

    def solve(self, read: ReadMeasurement) -> SolvedMeasurement:
        """Its solve (timed; the solver's lock held while it runs).

        Raises
        ------
        SolverError
        """
        return SolvedMeasurement(read, _solve(read.prepared, self._metrics, read.task))

    def answer(self, solved: SolvedMeasurement) -> Localization:
        """Its answer, each estimate labelled with its terminal when terminals were sent."""
        return _label(solved.read.prepared, solved.read.task, solved.solved)


@dataclass(frozen=True)
class ReadMeasurement:
    """A request body read by :meth:`RoomLocalizer.read`: its room version's prepared
    solver and what to solve."""

    prepared: PreparedVersion
    task: _Task


@dataclass(frozen=True)
class SolvedMeasurement:
    """A read body solved by :meth:`RoomLocalizer.solve`."""

    read: ReadMeasurement
    solved: _Solved


def localize_in_memory(
    cache: FingerprintCache,
    metrics: Metrics,
    *,
    room_id: str,
    body: Measurement,
    max_work: int | None = None,
    max_waitless_work: int = WAITLESS_WORK,
) -> Localization | None:
    """:func:`localize_measurement` when it can answer without waiting: its version and
    prepared solver in ``cache`` (no registry read, no load), the solver free (no other
    request solving with it) and the solve no more than ``max_waitless_work``
    (:func:`app.vlp.workload.localize_work` units) for at most :data:`WAITLESS_TARGETS`
    targets or terminals; else None, and nothing was done. The
    same answer and the same errors as :func:`localize_measurement` otherwise.

    Raises
    ------
    InvalidFields, MeasurementError, SolverError, ProblemSizeError
        As :func:`localize_measurement`.
    """
    form, model = input_form(body)
    found = cache.prepared_in_memory(room_id, body.fingerprint_version, model, body.solver)
    if found is None:
        return None
    version, prepared = found
    # Decided from the body's counts, before its measurement is made: a request that goes
    # to the pool is read there, once (50 terminals of a 1024-LED hall: ~10 ms each time).
    n_terminals = len(body.terminals) if body.terminals else None
    work = _work(prepared, model, n_terminals, body.targets)
    if work.units > max_waitless_work or work.targets > WAITLESS_TARGETS:
        return None
    task = _measurement_task(prepared, room_id, version, body, form, model)
    if max_work is not None:
        check_work(prepared, task, max_work)
    if not prepared.lock.acquire(blocking=False):
        return None
    try:
        return _solve_and_label(prepared, metrics, task, lock_held=True)
    finally:
        prepared.lock.release()


def _measurement_task(
    prepared: PreparedVersion,
    room_id: str,
    version: int,
    body: Measurement,
    form: str,
    model: Model,
) -> _Task:
    """The request body as a measurement of the fingerprint's LEDs (masked ones dropped).

    Raises
    ------
    InvalidFields, MeasurementError
    """
    n_leds = prepared.fingerprint.n_leds
    body = drop_masked_leds(body, prepared.masked_leds, n_leds)
    terminals = _terminal_set(body.terminals) if body.terminals else None
    if body.power is not None:
        measurement = measurement_from_power(body.power, n_leds)
    elif body.correlation is not None:
        measurement = measurement_from_correlation(body.correlation, n_leds)
    else:
        sent = np.zeros(0) if terminals is None else terminals.filled  # shape error
        try:
            measurement = measurement_from_amplitudes(sent, model, n_leds)
        except MeasurementError as exc:  # name the field the caller sent, not the aggregate
            raise MeasurementError(exc.message, field="terminals") from exc
    return _Task(room_id, version, measurement, body.solver, body.targets, terminals, form)


def localize_terminals(
    cache: FingerprintCache,
    metrics: Metrics,
    *,
    room_id: str,
    version: int,
    model: Model,
    solver: str,
    targets: int | None,
    terminals: TerminalSet,
    max_work: int | None = None,
) -> Localization:
    """Localize terminals' amplitudes (one per fingerprint LED) on (room, version), each
    estimate labelled with its terminal; ``targets`` None means one per terminal;
    ``max_work`` bounds the solve (:func:`check_work`)."""
    prepared = cache.prepare(room_id, version, model, solver)
    measurement = measurement_from_amplitudes(terminals.filled, model, prepared.fingerprint.n_leds)
    task = _Task(room_id, version, measurement, solver, targets, terminals, "terminals")
    if max_work is not None:
        check_work(prepared, task, max_work)
    return _solve_and_label(prepared, metrics, task)


def _terminal_set(sent: list[TerminalAmplitudes]) -> TerminalSet:
    """The terminals' amplitudes (one array), heights and unit normals.

    Raises
    ------
    InvalidFields
        Naming a terminal id sent twice, or a normal that is not a direction above the
        horizon.
    """
    ids = [terminal.id for terminal in sent]
    errors = [
        (f"terminals[{index}].id", f"terminal id {tid!r} appears more than once")
        for index, tid in enumerate(ids)
        if ids.index(tid) != index
    ]
    normals = []
    for index, terminal in enumerate(sent):
        vector = np.array(terminal.normal if terminal.normal is not None else (0.0, 0.0, 1.0))
        length = float(np.linalg.norm(vector))
        if not (np.isfinite(length) and length > 0.0 and vector[2] / length > 1e-6):
            errors.append(
                (
                    f"terminals[{index}].normal",
                    f"the photodiode's normal must point up (nz > 0), got {terminal.normal}",
                )
            )
            continue
        normals.append(vector / length)
    for index, terminal in enumerate(sent):
        errors += nothing_detected(terminal.amplitudes, field=f"terminals[{index}].amplitudes")
    if errors:
        raise InvalidFields(errors)
    heights = [np.nan if t.height is None else t.height for t in sent]
    return censored_terminal_set(
        ids,
        [t.amplitudes for t in sent],
        [t.detection_floor for t in sent],
        heights=None if all(t.height is None for t in sent) else np.array(heights),
        normals=None if all(t.normal is None for t in sent) else np.array(normals),
    )


def nothing_detected(amplitudes: Sequence[float | None], *, field: str) -> list[tuple[str, str]]:
    """The error for ``field`` when a terminal detected no LED (all its amplitudes null),
    else none: such a terminal says nothing about where it is."""
    if all(value is None for value in amplitudes):
        return [(field, "at least one LED must be detected (not null)")]
    return []


def censored_terminal_set(
    ids: Sequence[str],
    amplitudes: Sequence[Sequence[float | None]],
    floors: Sequence[float | None],
    *,
    heights: FloatArray | None = None,
    normals: FloatArray | None = None,
) -> TerminalSet:
    """Terminals' amplitudes as sent (None: an LED not detected) and their own detection
    floors (None: not sent) as a :class:`TerminalSet`, undetected LEDs as NaN.

    Parameters
    ----------
    ids : sequence of str, length K
    amplitudes : K sequences of M floats or None
    floors : K floats or None
    heights, normals : (K,), (K, 3) arrays or None
    """
    values = [[np.nan if a is None else a for a in row] for row in amplitudes]
    floor_values = [np.nan if floor is None else floor for floor in floors]
    return TerminalSet(
        ids=tuple(ids),
        amplitudes=np.array(values, dtype=np.float64),
        heights=heights,
        normals=normals,
        floors=None if all(floor is None for floor in floors) else np.array(floor_values),
    )


@dataclass(frozen=True)
class _Task:
    """What to solve: a validated measurement on (room, version) with the named solver."""

    room_id: str
    version: int
    measurement: MeasurementVector
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


def _per_terminal(prepared: PreparedVersion, task: _Task) -> bool:
    """Whether each terminal is fitted from its own amplitudes (labels known, not guessed)."""
    n_terminals = None if task.terminals is None else len(task.terminals.ids)
    return _fits_each_terminal(prepared, n_terminals, task.targets)


def _fits_each_terminal(
    prepared: PreparedVersion, n_terminals: int | None, targets: int | None
) -> bool:
    """:func:`_per_terminal` from the counts: ``n_terminals`` sent (None: no terminals) and
    the ``targets`` asked for."""
    return (
        n_terminals is not None
        and _terminal_solver(prepared.solver) is not None
        and targets in (None, n_terminals)
    )


def task_work(prepared: PreparedVersion, task: _Task) -> LocalizeWork:
    """The work a solve of ``task`` asks for (:func:`app.vlp.workload.localize_work`)."""
    n_terminals = None if task.terminals is None else len(task.terminals.ids)
    return _work(prepared, task.measurement.model, n_terminals, task.targets)


def _work(
    prepared: PreparedVersion, model: Model, n_terminals: int | None, targets: int | None
) -> LocalizeWork:
    """:func:`task_work` from the counts (as :func:`_fits_each_terminal`) and the model."""
    fingerprint = prepared.fingerprint
    per_terminal = _fits_each_terminal(prepared, n_terminals, targets)
    if targets is None and n_terminals is not None:
        targets = n_terminals
    return localize_work(
        n_cells=fingerprint.n_cells,
        n_leds=fingerprint.n_leds,
        model=model,
        targets=targets,
        terminals=n_terminals if per_terminal else None,
    )


def check_work(prepared: PreparedVersion, task: _Task, max_work: int) -> None:
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


def _solve_and_label(
    prepared: PreparedVersion, metrics: Metrics, task: _Task, *, lock_held: bool = False
) -> Localization:
    """Solve an aggregated measurement and, when the terminals' own amplitudes are known,
    label each estimate with its terminal (per-terminal fit, else an assignment problem).
    The solve holds ``prepared.lock`` (a solver solves one measurement at a time), unless
    the caller already does (``lock_held``)."""
    solved = _solve(prepared, metrics, task, lock_held=lock_held)
    return _label(prepared, task, solved)


@dataclass(frozen=True)
class _Solved:
    """A task's solution and the solver's time on it (seconds)."""

    solution: Solution
    elapsed_s: float


def _solve(
    prepared: PreparedVersion, metrics: Metrics, task: _Task, *, lock_held: bool = False
) -> _Solved:
    """The solve of :func:`_solve_and_label`, timed (the answer's ``elapsed_ms``)."""
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
    return _Solved(solution, elapsed)


def _label(prepared: PreparedVersion, task: _Task, solved: _Solved) -> Localization:
    """The answer of :func:`_solve_and_label`: the solution, each estimate labelled with
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
