"""Localization in batches: up to 1000 measurements of one room in one request.

The key is checked once and the room's current version read once for the whole batch; each
item then goes through the single localize's logic
(:func:`app.services.localization.localize_measurement`, called from one place,
``_Batch.solve``), in order, in one trip to the thread pool; its fingerprint and prepared
solver come from the in-memory cache. A bad item answers the
problem a single localize would have answered, in its place; the others are solved. Each
answer is encoded once, straight to JSON bytes by its model's serializer (as a single
localize's answer is), and the batch's body is those bytes joined.

What concerns the room rather than an item answers for the whole batch, as for a single
localize: 404 when the room does not exist, 409 while it has no ready fingerprint (when an
item needs the current one), 503 when the registry is unreachable.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from app.errors import CorruptMatrix, FingerprintNotFound, InvalidFields, VLPError
from app.schemas import Localization, LocalizationBatch, Measurement, MeasurementBatch
from app.services.fingerprint_cache import FingerprintCache
from app.services.localization import localize_measurement
from app.services.tracking import Tracking
from app.telemetry import Metrics

from .deps import AnyRole, CacheDep, MetricsDep, RoomId, SettingsDep
from .errors import ApiProblem, ProblemKind, as_problem, problem_body, problem_responses
from .json_body import FastJsonRoute
from .tracks import TrackingDep

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"], route_class=FastJsonRoute)


@dataclass
class _Batch:
    """What the batch's items share: the room, its current version (read once, when an item
    first needs it, so every item of the batch sees the same one) and the work bound."""

    room_id: str
    cache: FingerprintCache
    metrics: Metrics
    max_work: int
    tracking: Tracking
    current: int | None = None

    def solve(self, body: Measurement) -> bytes:
        """One item, through the single localize's logic (the one call to it), as the JSON
        a single localize answers."""
        if body.fingerprint_version is None:
            if self.current is None:
                self.current = self.cache.current_version(self.room_id)
            body = body.model_copy(update={"fingerprint_version": self.current})
        answer = localize_measurement(
            self.cache, self.metrics, room_id=self.room_id, body=body, max_work=self.max_work
        )
        if body.track:  # items update the tracks in their order
            answer = self.tracking.track(room_id=self.room_id, localization=answer, time=body.time)
        return Localization.__pydantic_serializer__.to_json(answer)


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


def _problem_json(problem: dict[str, Any]) -> bytes:
    """A problem item as JSON, written as a single localize's problem answer is."""
    return json.dumps(problem, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode(
        "utf-8"
    )


def _localize_batch(
    items: list[Any], batch: _Batch, instance: str, request_id: str | None
) -> Response:
    """The batch's answer, serialised here: a problem item carries only the members a
    problem answer has (no nulls), as a single localize's problem does."""
    answers: list[bytes] = []
    for index, item in enumerate(items):
        try:
            answers.append(batch.solve(Measurement.model_validate(item)))
        except _ITEM_ERRORS as exc:
            answers.append(_problem_json(_item_problem(exc, index, instance, request_id)))
    return Response(b'{"items":[' + b",".join(answers) + b"]}", media_type="application/json")


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
    batch = _Batch(room_id, cache, metrics, settings.max_localize_work, tracking)
    return await run_in_threadpool(
        _localize_batch,
        body.items,
        batch,
        request.url.path,
        getattr(request.state, "request_id", None),
    )
