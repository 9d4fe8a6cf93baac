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
prepared solver together) and solve through :mod:`app.services.solving` (the work bound,
the timed solve, the labelled answer), so they answer the same way. Each input rule is
checked once: the form and terminal ids and normals here, each terminal's amplitude count
in :mod:`app.services.masking`, shapes, signs and finiteness in :mod:`app.vlp.measurements`,
the work in :mod:`app.services.solving`, the target count in the solver.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.errors import InvalidFields
from app.schemas import Localization, Measurement, TerminalAmplitudes
from app.telemetry import Metrics
from app.vlp.errors import MeasurementError
from app.vlp.measurements import (
    Model,
    measurement_from_amplitudes,
    measurement_from_correlation,
    measurement_from_power,
)
from app.vlp.typing import FloatArray

from .fingerprint_cache import FingerprintCache, PreparedVersion
from .masking import drop_masked_leds
from .solving import (
    Solved,
    Task,
    TerminalSet,
    check_work,
    label_solution,
    solve_and_label,
    solve_task,
    task_work,
    work_from_counts,
)

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
        return SolvedMeasurement(read, solve_task(read.prepared, self._metrics, read.task))

    def answer(self, solved: SolvedMeasurement) -> Localization:
        """Its answer, each estimate labelled with its terminal when terminals were sent."""
        return label_solution(solved.read.prepared, solved.read.task, solved.solved)


@dataclass(frozen=True)
class ReadMeasurement:
    """A request body read by :meth:`RoomLocalizer.read`: its room version's prepared
    solver and what to solve."""

    prepared: PreparedVersion
    task: Task


@dataclass(frozen=True)
class SolvedMeasurement:
    """A read body solved by :meth:`RoomLocalizer.solve`."""

    read: ReadMeasurement
    solved: Solved


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
    work = work_from_counts(prepared, model, n_terminals, body.targets)
    if work.units > max_waitless_work or work.targets > WAITLESS_TARGETS:
        return None
    task = _measurement_task(prepared, room_id, version, body, form, model)
    if max_work is not None:
        check_work(prepared, task, max_work)
    if not prepared.lock.acquire(blocking=False):
        return None
    try:
        return solve_and_label(prepared, metrics, task, lock_held=True)
    finally:
        prepared.lock.release()


def _measurement_task(
    prepared: PreparedVersion,
    room_id: str,
    version: int,
    body: Measurement,
    form: str,
    model: Model,
) -> Task:
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
    return Task(room_id, version, measurement, body.solver, body.targets, terminals, form)


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
    task = Task(room_id, version, measurement, solver, targets, terminals, "terminals")
    if max_work is not None:
        check_work(prepared, task, max_work)
    return solve_and_label(prepared, metrics, task)


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
