"""Localization: a measurement in, the targets' positions out (the service logic is
:func:`app.services.localization.localize_measurement`).

A request whose room version and solver are in memory, whose solver is free and whose solve
is small (:data:`app.services.localization.WAITLESS_WORK`) is solved right here, on the
event loop: it would hold the GIL as long in a worker thread, and the hop there and back is
most of what the service adds around such a solve. Anything that may wait (a registry read,
a load, a busy solver, a large solve, the tracks' writes) goes to the thread pool.

The answer is encoded here, once, by its model's serializer (as each item of a batch is):
FastAPI would validate the model it was just built as and encode it again. The resources
come from the app's state, not one dependency each: each dependency FastAPI solves costs
more than the lookup it does.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from app.schemas import Localization, Measurement
from app.services.fingerprint_cache import FingerprintCache
from app.services.localization import localize_in_memory, localize_measurement
from app.services.tracking import Tracking
from app.settings import Settings
from app.telemetry import Metrics

from .deps import AnyRole, RoomId
from .errors import problem_responses
from .json_body import FastJsonRoute

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"], route_class=FastJsonRoute)


@router.post(
    "/{room_id}/localize",
    summary="Locate the targets behind a measurement",
    response_model=Localization,
    responses=problem_responses(401, 404, 409, 413, 422, 503),
)
async def localize(
    room_id: RoomId, body: Measurement, request: Request, _role: AnyRole
) -> Response:
    """Send exactly one of `power`, `correlation` (M x M or its upper triangle) or
    `terminals` (each terminal's amplitudes); get the targets' positions.

    Tip: `POST /v1/rooms/{room_id}/simulate` makes a ready-to-send body. 409 while the room
    has no ready fingerprint. With `track: true` the estimates also update the room's tracks
    (each carries `track_id` and `tracked`).
    """
    state = request.app.state
    cache: FingerprintCache = state.cache
    metrics: Metrics = state.metrics
    settings: Settings = state.settings
    answer = localize_in_memory(
        cache, metrics, room_id=room_id, body=body, max_work=settings.max_localize_work
    )
    if answer is None:
        answer = await run_in_threadpool(
            localize_measurement,
            cache,
            metrics,
            room_id=room_id,
            body=body,
            max_work=settings.max_localize_work,
        )
    if body.track:
        tracking: Tracking = state.tracking
        answer = await run_in_threadpool(
            tracking.track, room_id=room_id, localization=answer, time=body.time
        )
    return Response(
        Localization.__pydantic_serializer__.to_json(answer), media_type="application/json"
    )
