"""Localization: a measurement in, the targets' positions out."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.schemas import Estimate, Fit, Localization, Measurement, TerminalAmplitudes
from app.vlp import measurements as vlp_measurements
from app.vlp._typing import FloatArray
from app.vlp.assignment import assign_terminals
from app.vlp.errors import MeasurementError
from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import Model
from app.vlp.solvers import Solution, solver_names
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.uncertainty import confidence_radius

from .deps import AnyRole, CacheDep, MetricsDep, RoomId
from .errors import InvalidInput, problem_responses
from .localizer import FingerprintCache
from .masking import drop_masked_leds
from .metrics import Metrics

__all__ = ["TerminalSet", "input_form", "require_installed", "router", "solve_and_label"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"])
_FORMS = ("power", "correlation", "terminals")


@dataclass(frozen=True)
class _Request:
    room_id: str
    body: Measurement
    form: str
    model: Model


def input_form(body: Measurement) -> tuple[str, Model]:
    """Which of ``power``/``correlation``/``terminals`` was sent, and the model it implies.

    Raises
    ------
    InvalidInput
        Unless exactly one was sent, or when ``model`` contradicts it.
    """
    sent = [form for form in _FORMS if getattr(body, form) is not None]
    if len(sent) != 1:
        names = sent or list(_FORMS)
        what = "none of them was" if not sent else f"{len(sent)} were"
        raise InvalidInput(
            [
                (f"body.{form}", f"send exactly one of power, correlation, terminals; {what} sent")
                for form in names
            ]
        )
    form = sent[0]
    explicit = "model" in body.model_fields_set
    if form == "terminals":
        return form, body.model
    implied: Model = "power" if form == "power" else "correlation"
    if explicit and body.model != implied:
        raise InvalidInput(
            [
                (
                    "body.model",
                    f"model {body.model!r} does not fit `{form}`; "
                    f"use model {implied!r} or leave it out",
                )
            ]
        )
    return form, implied


def require_installed(solver: str) -> None:
    """422 naming ``body.solver`` when that solver is not installed on this server."""
    if solver not in solver_names():
        raise InvalidInput(
            [
                (
                    "body.solver",
                    f"solver {solver!r} is not installed on this server; "
                    f"choose one of {solver_names()}",
                )
            ]
        )


def _measurement(request: _Request, n_leds: int) -> vlp_measurements.Measurement:
    body = request.body
    if request.form == "power":
        return vlp_measurements.measurement_from_power(body.power, n_leds)
    if request.form == "correlation":
        return vlp_measurements.measurement_from_correlation(body.correlation, n_leds)
    terminals = body.terminals or []
    errors = [
        (
            f"body.terminals.{index}.amplitudes",
            f"expected {n_leds} amplitudes (one per LED), got {len(terminal.amplitudes)}",
        )
        for index, terminal in enumerate(terminals)
        if len(terminal.amplitudes) != n_leds
    ]
    ids = [terminal.id for terminal in terminals]
    errors += [
        (f"body.terminals.{index}.id", f"terminal id {tid!r} appears more than once")
        for index, tid in enumerate(ids)
        if ids.index(tid) != index
    ]
    if errors:
        raise InvalidInput(errors)
    amplitudes = np.array([terminal.amplitudes for terminal in terminals], dtype=np.float64)
    try:
        return vlp_measurements.measurement_from_amplitudes(amplitudes, request.model, n_leds)
    except MeasurementError as exc:  # name the field the caller sent, not the aggregate
        raise InvalidInput([("body.terminals", exc.message)]) from exc


def _localize(request: _Request, cache: FingerprintCache, metrics: Metrics) -> Localization:
    body = request.body
    version = body.fingerprint_version or cache.current_version(request.room_id)
    fingerprint, masked = cache.fingerprint_and_mask(request.room_id, version)
    if masked:  # sent for the room's M LEDs: drop the entries the fingerprint leaves out
        body = drop_masked_leds(body, masked, fingerprint.n_leds)
        request = _Request(request.room_id, body, request.form, request.model)
    measurement = _measurement(request, fingerprint.n_leds)
    terminals = None
    if body.terminals:
        terminals = _terminal_set(body.terminals)
    return solve_and_label(
        cache,
        metrics,
        fingerprint=fingerprint,
        room_id=request.room_id,
        version=version,
        measurement=measurement,
        solver=body.solver,
        targets=body.targets,
        terminals=terminals,
    )


def _terminal_set(sent: list[TerminalAmplitudes]) -> TerminalSet:
    """The terminals' amplitudes, heights and unit normals (422 naming a normal that is
    not a direction above the horizon)."""
    errors = []
    normals = []
    for index, terminal in enumerate(sent):
        vector = np.array(terminal.normal if terminal.normal is not None else (0.0, 0.0, 1.0))
        length = float(np.linalg.norm(vector))
        if not (np.isfinite(length) and length > 0.0 and vector[2] / length > 1e-6):
            errors.append(
                (
                    f"body.terminals.{index}.normal",
                    f"the photodiode's normal must point up (nz > 0), got {terminal.normal}",
                )
            )
            continue
        normals.append(vector / length)
    if errors:
        raise InvalidInput(errors)
    heights = [np.nan if t.height is None else t.height for t in sent]
    return TerminalSet(
        ids=tuple(terminal.id for terminal in sent),
        amplitudes=np.array([terminal.amplitudes for terminal in sent], dtype=np.float64),
        heights=None if all(t.height is None for t in sent) else np.array(heights),
        normals=None if all(t.normal is None for t in sent) else np.array(normals),
    )


@dataclass(frozen=True)
class TerminalSet:
    """Terminals' own amplitudes: ``amplitudes[k]`` (M numbers) were sent by ``ids[k]``;
    ``heights[k]`` (NaN: unknown) and ``normals[k]`` (unit vectors) when they sent them."""

    ids: tuple[str, ...]
    amplitudes: FloatArray
    heights: FloatArray | None = None
    normals: FloatArray | None = None


def solve_and_label(
    cache: FingerprintCache,
    metrics: Metrics,
    *,
    fingerprint: Fingerprint,
    room_id: str,
    version: int,
    measurement: vlp_measurements.Measurement,
    solver: str,
    targets: int | None,
    terminals: TerminalSet | None,
) -> Localization:
    """Solve an aggregated measurement on (room, version) and, when the terminals' own
    amplitudes are known, label each estimate with its terminal (an assignment problem).

    Used by localize and by epochs, so both answer the same way. ``fingerprint`` is the
    caller's (room, version) fingerprint, already looked up.
    """
    prepared = cache.solver(room_id, version, measurement.model, solver)
    if terminals is not None and targets is None:
        targets = len(terminals.ids)  # the contract: one target per terminal sent
    per_terminal = (
        terminals is not None
        and isinstance(prepared.solver, GridlessSolver)
        and targets == len(terminals.ids)
    )
    with prepared.lock:
        started = time.perf_counter()
        if per_terminal and terminals is not None and isinstance(prepared.solver, GridlessSolver):
            solution = prepared.solver.solve_terminals(
                terminals.amplitudes, terminals.heights, terminals.normals
            )
        else:
            solution = prepared.solver.solve(measurement, targets)
        elapsed = time.perf_counter() - started
    metrics.localize_latency.labels(solver=solver, model=measurement.model).observe(elapsed)
    owners: list[str | None] = [None] * solution.n_targets
    if per_terminal and terminals is not None:
        owners = list(terminals.ids)
    elif terminals is not None:
        assigned = assign_terminals(fingerprint.layout, solution.positions, terminals.amplitudes)
        owners = [terminals.ids[int(index)] if index >= 0 else None for index in assigned]
    return Localization(
        room_id=room_id,
        fingerprint_version=version,
        model=measurement.model,
        solver=solver,
        targets=solution.n_targets,
        estimates=_estimates(solution, owners),
        residual_norm=float(solution.residual_norm),
        noise_power=float(solution.noise_power),
        elapsed_ms=round(elapsed * 1e3, 3),
        fit=None if solution.fit is None else Fit(**dataclasses.asdict(solution.fit)),
    )


def _estimates(solution: Solution, owners: list[str | None]) -> list[Estimate]:
    """The answer's estimates, with their uncertainty, gain and height when the solver
    gives them."""
    estimates = []
    for k in range(solution.n_targets):
        covariance = None if solution.covariances is None else solution.covariances[k]
        estimates.append(
            Estimate(
                x=float(solution.positions[k, 0]),
                y=float(solution.positions[k, 1]),
                grid_index=int(solution.grid_indices[k]),
                weight=float(solution.weights[k]),
                terminal_id=owners[k],
                accuracy_m=None if covariance is None else confidence_radius(covariance),
                covariance=None if covariance is None else covariance.tolist(),
                gain=None if solution.gains is None else float(solution.gains[k]),
                z=None if solution.heights is None else float(solution.heights[k]),
            )
        )
    return estimates


@router.post(
    "/{room_id}/localize",
    summary="Locate the targets behind a measurement",
    responses=problem_responses(401, 404, 409, 413, 422, 503),
)
async def localize(
    room_id: RoomId, body: Measurement, cache: CacheDep, metrics: MetricsDep, _role: AnyRole
) -> Localization:
    """Send exactly one of `power`, `correlation` (M x M or its upper triangle) or
    `terminals` (each terminal's amplitudes); get the targets' positions.

    Tip: `POST /v1/rooms/{room_id}/simulate` makes a ready-to-send body. 409 while the room
    has no ready fingerprint.
    """
    form, model = input_form(body)
    require_installed(body.solver)
    request = _Request(room_id=room_id, body=body, form=form, model=model)
    return await run_in_threadpool(_localize, request, cache, metrics)
