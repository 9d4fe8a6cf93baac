"""Rooms: create, list, read, replace (with ``If-Match``) and delete."""

from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Response, status

from app.registry import RoomRecord
from app.schemas import FingerprintState, Room, RoomLayout, RoomsPage
from app.settings import Settings
from app.vlp.layout import layout_from_mapping

from .deps import AdminRole, AnyRole, CacheDep, RegistryDep, RoomId, SettingsDep
from .errors import ApiProblem, InvalidInput, ProblemKind, problem_responses

__all__ = ["room_public", "router", "validated_layout"]

router = APIRouter(prefix="/v1/rooms", tags=["rooms"])


def room_public(record: RoomRecord) -> Room:
    """The public form of a room record."""
    return Room(
        id=record.id,
        name=record.name,
        layout=record.layout,
        layout_version=record.layout_version,
        created_at=record.created_at,
        updated_at=record.updated_at,
        fingerprint=FingerprintState(
            status=record.fingerprint_status,
            version=record.fingerprint_version,
            job_id=record.job_id,
        ),
    )


def validated_layout(body: RoomLayout, settings: Settings) -> dict[str, Any]:
    """The layout mapping with defaults applied, after the size limits and geometry checks.

    The grid size is computed from the numbers alone, before anything is allocated.
    """
    if len(body.leds) > settings.max_leds:
        raise InvalidInput(
            [("body.leds", f"at most {settings.max_leds} LEDs are allowed, got {len(body.leds)}")]
        )
    step = body.grid.step
    points = (body.room.length / step) * (body.room.width / step)
    if not math.isfinite(points) or points > settings.max_grid_points * (1 + 1e-9):
        raise InvalidInput(
            [
                (
                    "body.grid.step",
                    f"grid.step {step!r} m gives about {points:.3g} grid points; at "
                    f"most {settings.max_grid_points} are allowed",
                )
            ]
        )
    layout = layout_from_mapping(body.model_dump())
    return layout.to_mapping()


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
    record = registry.create_room(name=body.name, layout=validated_layout(body, settings))
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
    if if_none_match is not None and _matches(if_none_match, record.etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers={"ETag": record.etag})
    response.headers["ETag"] = record.etag
    return room_public(record)


def _matches(if_match: str, etag: str) -> bool:
    candidates = [part.strip() for part in if_match.split(",")]
    return "*" in candidates or etag in candidates


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
    layout = validated_layout(body, settings)
    current = registry.get_room(room_id=room_id)
    if not _matches(if_match, current.etag):
        raise ApiProblem(
            412,
            f"If-Match {if_match} is not the room's current ETag "
            f"{current.etag}; read the room again",
            kind=ProblemKind.PRECONDITION_FAILED,
        )
    record = registry.replace_room(
        room_id=room_id,
        name=body.name,
        layout=layout,
        expected_layout_version=current.layout_version,
    )
    cache.forget(room_id)
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
