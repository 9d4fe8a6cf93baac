"""Rooms: create, list, read, replace (with ``If-Match``) and delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Response, status

from app.registry import RoomRecord
from app.schemas import Room, RoomLayout, RoomsPage
from app.services import rooms as room_service
from app.services.public import room_public

from .deps import AdminRole, AnyRole, CacheDep, RegistryDep, RoomId, SettingsDep
from .errors import ApiProblem, ProblemKind, problem_responses

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["rooms"])


def _set_room_headers(response: Response, record: RoomRecord) -> None:
    response.headers["ETag"] = record.etag
    response.headers["Location"] = f"/v1/rooms/{record.id}"


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    summary="Create a room",
    responses={
        201: {
            "headers": {
                "Location": {"schema": {"type": "string"}},
                "ETag": {"schema": {"type": "string"}},
            }
        },
        **problem_responses(401, 403, 413, 422),
    },
)
def create_room(
    body: RoomLayout,
    response: Response,
    registry: RegistryDep,
    settings: SettingsDep,
    _role: AdminRole,
) -> Room:
    """Create a room from its layout and queue its first fingerprint build.

    The answer's `fingerprint.job_id` is the build job; the room can localize once
    `fingerprint.status` is `ready`.
    """
    record = room_service.create_room(registry, body=body, settings=settings)
    _set_room_headers(response, record)
    return room_public(record)


@router.get("", summary="List rooms", responses=problem_responses(401, 422))
def list_rooms(
    registry: RegistryDep,
    _role: AnyRole,
    limit: Annotated[int, Query(ge=1, le=100, description="page size")] = 20,
    cursor: Annotated[
        str | None, Query(max_length=512, description="`next_cursor` of the previous page")
    ] = None,
) -> RoomsPage:
    """Rooms, oldest first, one page at a time."""
    records, next_cursor = registry.list_rooms(limit=limit, cursor=cursor)
    return RoomsPage(items=[room_public(record) for record in records], next_cursor=next_cursor)


@router.get(
    "/{room_id}",
    summary="Read a room",
    response_model=Room,
    responses={
        200: {"headers": {"ETag": {"schema": {"type": "string"}}}},
        304: {
            "description": "`If-None-Match` names the room's current `ETag`: unchanged, no body",
            "headers": {"ETag": {"schema": {"type": "string"}}},
        },
        **problem_responses(401, 404),
    },
)
def get_room(
    room_id: RoomId,
    response: Response,
    registry: RegistryDep,
    _role: AnyRole,
    if_none_match: Annotated[
        str | None, Header(description="an `ETag` read before: 304 while it is still current")
    ] = None,
) -> Room | Response:
    """The room, with its `ETag` (send it back in `If-Match` to replace the room, or in
    `If-None-Match` to get a bodiless 304 while the room is unchanged)."""
    record = registry.get_room(room_id=room_id)
    if if_none_match is not None and room_service.etag_matches(if_none_match, record.etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers={"ETag": record.etag})
    response.headers["ETag"] = record.etag
    return room_public(record)


@router.put(
    "/{room_id}",
    summary="Replace a room's layout",
    responses={
        200: {"headers": {"ETag": {"schema": {"type": "string"}}}},
        **problem_responses(401, 403, 404, 412, 413, 422, 428),
    },
)
def replace_room(
    room_id: RoomId,
    body: RoomLayout,
    response: Response,
    registry: RegistryDep,
    settings: SettingsDep,
    cache: CacheDep,
    _role: AdminRole,
    if_match: Annotated[str | None, Header(description="the room's current `ETag`")] = None,
) -> Room:
    """Replace the whole layout; the room gets a new `layout_version` and a new build.

    Localization keeps using the previous fingerprint until the new one is ready.
    """
    if if_match is None:
        raise ApiProblem(
            428,
            "send the room's current ETag in If-Match to replace it",
            kind=ProblemKind.PRECONDITION_REQUIRED,
        )
    record = room_service.replace_room(
        registry, cache, room_id=room_id, body=body, settings=settings, if_match=if_match
    )
    _set_room_headers(response, record)
    return room_public(record)


@router.delete(
    "/{room_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    summary="Delete a room",
    responses=problem_responses(401, 403, 404),
)
def delete_room(
    room_id: RoomId, registry: RegistryDep, cache: CacheDep, _role: AdminRole
) -> Response:
    """Delete the room with its fingerprints and jobs."""
    registry.delete_room(room_id=room_id)
    cache.forget(room_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
