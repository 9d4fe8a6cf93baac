"""Localization in batches: up to 1000 measurements of one room in one request.

The key is checked once; in one trip to the thread pool the items then go through the single
localize's logic (:class:`app.services.localization.RoomLocalizer`, which reads the room's
current version once and looks each prepared solver up once for the whole batch) in three
passes: all read (validated in one call, each on its own only when one of them is bad, and
made measurements), all solved back to back, all answered in order (the tracks too). A bad
item answers the problem a single localize would have answered, in its place; the others are
solved. The answers are encoded in one call by their model's serializer when none is a
problem, else each on its own, and joined. What a batch holds at once is bounded by its
body (``VLP_MAX_BODY_BYTES``): each item's measurement, and its solution's few arrays.

What concerns the room rather than an item answers for the whole batch, as for a single
localize: 404 when the room does not exist, 409 while it has no ready fingerprint (when an
item needs the current one), 503 when the registry is unreachable.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import TypeAdapter, ValidationError
from starlette.concurrency import run_in_threadpool

from app.errors import CorruptMatrix, FingerprintNotFound, InvalidFields, VLPError
from app.schemas import Localization, LocalizationBatch, Measurement, MeasurementBatch
from app.services.localization import ReadMeasurement, RoomLocalizer, SolvedMeasurement
from app.services.tracking import Tracking

from .deps import AnyRole, CacheDep, MetricsDep, RoomId, SettingsDep
from .errors import ApiProblem, ProblemKind, as_problem, problem_body, problem_responses
from .json_body import FastJsonRoute
from .tracks import TrackingDep

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"], route_class=FastJsonRoute)


@dataclass
class _Batch:
    """What the batch's items share: the room's localizer (its current version read once,
    when an item first needs it, so every item sees the same one; each prepared solver
    looked up once), the tracks, and what a problem item names (the request's path and
    id)."""

    room_id: str
    localizer: RoomLocalizer
    tracking: Tracking
    instance: str
    request_id: str | None

    def problem(self, exc: Exception, index: int) -> bytes:
        """The problem of the item at ``index``, as JSON."""
        return _problem_json(_item_problem(exc, index, self.instance, self.request_id))

    def answer(self, body: Measurement, solved: SolvedMeasurement) -> Localization:
        """A solved item's answer, as a single localize answers it (its tracks updated
        first when it asks)."""
        answer = self.localizer.answer(solved)
        if body.track:
            answer = self.tracking.track(room_id=self.room_id, localization=answer, time=body.time)
        return answer


def _in_item(location: str, index: int) -> str:
    """A single request's field (``body.power``) as the batch's (``body.items.3.power``)."""
    head, _, rest = location.partition(".")
    if head != "body":
        return f"body.items.{index}"
    return f"body.items.{index}.{rest}" if rest else f"body.items.{index}"


def _item_problem(
    exc: Exception, index: int, instance: str, request_id: str | None
) -> dict[str, Any]:
    """The problem of a bad item, as a single localize would answer it, fields renamed."""
    if isinstance(exc, ValidationError):
        errors = [
            (
                _in_item(".".join(["body", *(str(part) for part in error["loc"])]), index),
                error["msg"],
            )
            for error in exc.errors()
        ]
        detail = f"{len(errors)} invalid input(s): " + "; ".join(f"{f}: {m}" for f, m in errors)
        problem = ApiProblem(
            422, detail, kind=ProblemKind.VALIDATION, title="Validation failed", errors=errors
        )
    else:
        mapped = as_problem(exc)
        problem = ApiProblem(
            mapped.status,
            mapped.detail,
            kind=mapped.kind,
            title=mapped.title,
            errors=[(_in_item(location, index), message) for location, message in mapped.errors],
        )
    return problem_body(
        problem.status,
        problem.detail,
        instance=instance,
        kind=problem.kind,
        title=problem.title,
        errors=problem.errors,
        request_id=request_id,
    )


# An item's own faults; what concerns the room (no such room, no ready fingerprint, registry
# away) answers for the whole batch, as for a single localize.
_ITEM_ERRORS = (
    ValidationError,
    ApiProblem,
    InvalidFields,
    VLPError,
    FingerprintNotFound,
    CorruptMatrix,
)


# The items as measurements, validated in one call when all of them are good; the answers
# encoded in one call when all of them are localizations.
_MEASUREMENTS = TypeAdapter(list[Measurement])
_LOCALIZATIONS = TypeAdapter(list[Localization])


def _problem_json(problem: dict[str, Any]) -> bytes:
    """A problem item as JSON, written as a single localize's problem answer is."""
    return json.dumps(problem, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode(
        "utf-8"
    )


def _localize_batch(items: list[Any], batch: _Batch) -> Response:
    """The batch's answer, in three passes over its items: each read (validated, its
    measurement made), each solved, back to back, each answered, in order (the tracks too);
    then encoded in one call when every item was answered, else each on its own (a problem
    item carries only the members a problem answer has, no nulls, as a single localize's
    problem does)."""
    answers: list[Localization | bytes] = [b""] * len(items)
    read: list[tuple[int, Measurement, ReadMeasurement]] = []
    for index, body in _measurements(items):
        try:
            if not isinstance(body, Measurement):
                body = Measurement.model_validate(body)
            read.append((index, body, batch.localizer.read(body)))
        except _ITEM_ERRORS as exc:
            answers[index] = batch.problem(exc, index)
    solved: list[tuple[int, Measurement, SolvedMeasurement]] = []
    for index, body, measurement in read:
        try:
            solved.append((index, body, batch.localizer.solve(measurement)))
        except _ITEM_ERRORS as exc:
            answers[index] = batch.problem(exc, index)
    for index, body, solution in solved:
        try:
            answers[index] = batch.answer(body, solution)
        except _ITEM_ERRORS as exc:
            answers[index] = batch.problem(exc, index)
    return Response(b'{"items":' + _encoded(answers) + b"}", media_type="application/json")


def _encoded(answers: list[Localization | bytes]) -> bytes:
    """The answers as a JSON array: one serializer call for the localizations when there is
    no problem among them (the same bytes as each encoded on its own and joined)."""
    if len(solved := [a for a in answers if isinstance(a, Localization)]) == len(answers):
        return _LOCALIZATIONS.dump_json(solved)
    encode = Localization.__pydantic_serializer__.to_json
    parts = [a if isinstance(a, bytes) else encode(a) for a in answers]
    return b"[" + b",".join(parts) + b"]"


def _measurements(items: list[Any]) -> enumerate[Measurement | Any]:
    """The items as measurements, validated in one call when every one is good; else as
    sent, each to be validated on its own (to answer its problem in its place)."""
    try:
        return enumerate(_MEASUREMENTS.validate_python(items))
    except ValidationError:
        return enumerate(items)


@router.post(
    "/{room_id}/localize/batch",
    summary="Locate the targets behind many measurements at once",
    response_model=LocalizationBatch,
    responses=problem_responses(401, 404, 409, 413, 422, 503),
)
async def localize_batch(
    room_id: RoomId,
    body: MeasurementBatch,
    request: Request,
    cache: CacheDep,
    metrics: MetricsDep,
    settings: SettingsDep,
    tracking: TrackingDep,
    _role: AnyRole,
) -> Response:
    """Send `{"items": [Measurement, ...]}` (1 to 1000, each as the body of
    `POST /v1/rooms/{room_id}/localize`); get `{"items": [...]}` in the same order: each a
    `Localization`, or the problem (with its `status`) that a single localize of that item
    would have answered, without failing the others.

    For many terminals at once this saves the per-request cost (HTTP, key check, room
    lookup) of single calls. 409 while the room has no ready fingerprint.
    """
    batch = _Batch(
        room_id,
        RoomLocalizer(cache, metrics, room_id=room_id, max_work=settings.max_localize_work),
        tracking,
        request.url.path,
        getattr(request.state, "request_id", None),
    )
    return await run_in_threadpool(_localize_batch, body.items, batch)
