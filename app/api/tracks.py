"""Tracks of a room: list, read, history, end, settings, and the live event stream.

The service logic is :mod:`app.services.tracking`; the stream reads the room's events from
the registry and waits on :class:`app.services.track_stream.TrackEventHub` between reads.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response, status
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import AwareDatetime
from starlette.concurrency import run_in_threadpool
from starlette.convertors import Convertor, register_url_convertor

from app.schemas import (
    AccuracyMap,
    Track,
    TrackingSettings,
    TrackingSettingsUpdate,
    TrackPointsPage,
    TracksPage,
)
from app.schemas.tracking import TRACK_STATUSES, TrackStatus
from app.services import track_resources
from app.services.track_stream import TrackEventHub
from app.services.tracking import Tracking

from .deps import AdminRole, AnyRole, RegistryDep, RoomId
from .errors import InvalidInput, problem_responses

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["tracking"])

# Events read from the registry at once by a stream (more wait for the next read).
_STREAM_BATCH = 500
# A client that loses the stream reconnects after this long, milliseconds.
_RETRY_MS = 1000

TrackId = Annotated[
    str,
    Path(
        pattern="^[0-9a-f]{32}$",
        description="the track's id (32 hex digits)",
        examples=["5d0c1f2e3a4b4c6d8e9f0a1b2c3d4e5f"],
    ),
]


class _TrackIdConvertor(Convertor[str]):
    """Track ids are 32 hex digits: so `/tracks/stream` is never taken for a track's path."""

    regex = "[0-9a-f]{32}"

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("track_id", _TrackIdConvertor())


async def get_tracking(request: Request) -> Tracking:
    """The tracking service built in the lifespan (``async``: no thread-pool hop, as in
    :mod:`app.api.deps`)."""
    tracking: Tracking = request.app.state.tracking
    return tracking


async def get_hub(request: Request) -> TrackEventHub:
    """This process's stream hub."""
    hub: TrackEventHub = request.app.state.track_hub
    return hub


TrackingDep = Annotated[Tracking, Depends(get_tracking)]
HubDep = Annotated[TrackEventHub, Depends(get_hub)]


@router.get(
    "/{room_id}/tracks",
    summary="List a room's tracks",
    responses=problem_responses(401, 404, 422, 503),
)
def list_tracks(
    room_id: RoomId,
    registry: RegistryDep,
    _role: AnyRole,
    status_: Annotated[
        list[TrackStatus] | None,
        Query(alias="status", description="default: `tentative` and `confirmed`"),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="page size")] = 100,
    cursor: Annotated[
        str | None, Query(max_length=512, description="`next_cursor` of the previous page")
    ] = None,
) -> TracksPage:
    """The room's tracks, oldest first; `?status=lost` (repeatable) for other statuses."""
    statuses = tuple(status_) if status_ else TRACK_STATUSES[:2]
    return track_resources.list_tracks(
        registry, room_id=room_id, statuses=statuses, limit=limit, cursor=cursor
    )


async def _stream_start(
    room_id: RoomId,
    registry: RegistryDep,
    last_event_id: Annotated[
        str | None,
        Header(
            alias="Last-Event-ID",
            max_length=20,
            description="the `id` of the last event received: the stream resumes after it",
        ),
    ] = None,
) -> int | None:
    """Checks made before the stream starts (so they answer as problems): the room exists
    and ``Last-Event-ID`` is a sequence number. None: no ``Last-Event-ID``."""
    if last_event_id is not None and not last_event_id.strip().isdigit():
        raise InvalidInput(
            [
                (
                    "header.Last-Event-ID",
                    f"expected an event id (a whole number), got {last_event_id!r}",
                )
            ]
        )
    await run_in_threadpool(registry.get_room, room_id=room_id)
    return None if last_event_id is None else int(last_event_id)


@router.get(
    "/{room_id}/tracks/stream",
    summary="Follow a room's tracks live (Server-Sent Events)",
    response_class=EventSourceResponse,
    responses={
        200: {
            "description": "`text/event-stream`: `track` events (data: `Track`) and "
            '`removed` events (data: `{"id"}`), each with its per-room sequence as `id`'
        },
        **problem_responses(401, 404, 422, 503),
    },
)
async def stream_tracks(
    room_id: RoomId,
    request: Request,
    registry: RegistryDep,
    hub: HubDep,
    _role: AnyRole,
    resume_after: Annotated[int | None, Depends(_stream_start)],
) -> AsyncIterator[ServerSentEvent]:
    """An event `track` (data: the `Track`) each time a track of the room changes and
    `removed` (data: `{"id"}`) when one ends, made by any API process. Each event's `id` is
    the room's sequence number: reconnect with `Last-Event-ID` to receive what was missed
    (within the room's `history_s`). Without it, the stream opens with the room's current
    tentative and confirmed tracks (events `track` whose `id` is the sequence they were read
    at), then follows.
    """
    if resume_after is None:
        after = await run_in_threadpool(registry.tracks.latest_sequence, room_id=room_id)
        page = await run_in_threadpool(
            track_resources.list_tracks,
            registry,
            room_id=room_id,
            statuses=TRACK_STATUSES[:2],
            limit=1000,
            cursor=None,
        )
        for item in page.items:
            yield ServerSentEvent(
                event="track", id=str(after), raw_data=item.model_dump_json(), retry=_RETRY_MS
            )
    else:
        after = resume_after
    while not await request.is_disconnected():
        events = await run_in_threadpool(
            track_resources.events_since,
            registry,
            room_id=room_id,
            after=after,
            limit=_STREAM_BATCH,
        )
        for event in events:
            yield ServerSentEvent(
                event=event.kind,
                id=str(event.sequence),
                raw_data=json.dumps(event.data, separators=(",", ":")),
            )
            after = event.sequence
        if len(events) < _STREAM_BATCH:
            await hub.wait(room_id, after)


@router.get(
    "/{room_id}/tracks/{track_id:track_id}",
    summary="Read a track",
    responses=problem_responses(401, 404, 503),
)
def get_track(room_id: RoomId, track_id: TrackId, registry: RegistryDep, _role: AnyRole) -> Track:
    """One track of the room (404 once it has ended)."""
    return track_resources.get_track(registry, room_id=room_id, track_id=track_id)


@router.get(
    "/{room_id}/tracks/{track_id:track_id}/points",
    summary="Read a track's recent history",
    responses=problem_responses(401, 404, 422, 503),
)
def get_track_points(
    room_id: RoomId,
    track_id: TrackId,
    registry: RegistryDep,
    _role: AnyRole,
    since: Annotated[
        AwareDatetime | None, Query(description="only points from this time on (RFC 3339)")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=5000, description="page size")] = 1000,
    cursor: Annotated[
        str | None, Query(max_length=32, description="`next_cursor` of the previous page")
    ] = None,
) -> TrackPointsPage:
    """The track's state after each estimate that reached it, and that estimate (`raw`),
    oldest first, within the room's `history_s`."""
    return track_resources.track_points(
        registry, room_id=room_id, track_id=track_id, since=since, limit=limit, cursor=cursor
    )


@router.delete(
    "/{room_id}/tracks/{track_id:track_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    summary="End a track",
    responses=problem_responses(401, 403, 404, 503),
)
def delete_track(
    room_id: RoomId, track_id: TrackId, tracking: TrackingDep, _role: AdminRole
) -> Response:
    """End the track now: its history goes and the stream says `removed`. A terminal that
    sends again starts a new track (a new id)."""
    tracking.delete(room_id=room_id, track_id=track_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get(
    "/{room_id}/tracking",
    summary="Read a room's tracking settings",
    responses=problem_responses(401, 404, 503),
)
def get_tracking_settings(
    room_id: RoomId, registry: RegistryDep, _role: AnyRole
) -> TrackingSettings:
    """Motion limits, gates, timeouts and history of the room's tracks, as in force."""
    return track_resources.tracking_settings(registry, room_id=room_id)


@router.put(
    "/{room_id}/tracking",
    summary="Change a room's tracking settings",
    responses=problem_responses(401, 403, 404, 413, 422, 503),
)
def put_tracking_settings(
    room_id: RoomId,
    body: TrackingSettingsUpdate,
    registry: RegistryDep,
    _role: AdminRole,
) -> TrackingSettings:
    """The fields sent replace those in force (`null`: back to the default); the others
    stay. Fingerprints are not rebuilt; tracks keep their state."""
    return track_resources.update_tracking_settings(registry, room_id=room_id, body=body)


@router.get(
    "/{room_id}/tracking/accuracy",
    summary="Read a room's accuracy map",
    responses=problem_responses(401, 404, 503),
)
def get_accuracy_map(room_id: RoomId, registry: RegistryDep, _role: AnyRole) -> AccuracyMap:
    """The bound on how accurately one terminal can be placed from its own amplitudes, on
    blocks of the grid: the live view draws it behind the tracks."""
    return track_resources.accuracy_map(registry, room_id=room_id)
