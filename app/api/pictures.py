"""Pictures: the room plan (``map.png``) and estimates against the truth (``localization.png``).

What is drawn, and how plans are cached, is :mod:`app.services.pictures`.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Response
from starlette.concurrency import run_in_threadpool

from app.schemas import LocalizationPlot
from app.schemas.common import MAX_VERSION
from app.services.pictures import localization_picture as draw_localization
from app.services.pictures import room_map as draw_room_map

from .deps import AnyRole, CacheDep, PicturesDep, RegistryDep, RoomId
from .errors import problem_responses

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms/{room_id}", tags=["pictures"])

_PNG: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "a PNG picture",
        "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
        "headers": {
            "ETag": {"schema": {"type": "string"}, "description": "hash of the PNG bytes"},
            "X-Fingerprint-Version": {
                "schema": {"type": "string"},
                "description": "the version whose layout is drawn (absent: the room's layout)",
            },
        },
    }
}


def _headers(etag: str, version: int | None, *, pinned: bool) -> dict[str, str]:
    headers = {
        "ETag": etag,
        # A pinned version never changes; "current" may move on, so revalidate (ETag).
        "Cache-Control": "private, max-age=31536000, immutable" if pinned else "private, no-cache",
    }
    if version is not None:
        headers["X-Fingerprint-Version"] = str(version)
    return headers


@router.get(
    "/map.png",
    summary="Draw the room plan",
    response_class=Response,
    responses={**_PNG, 304: {"description": "not modified (`If-None-Match`)"}}
    | problem_responses(401, 404, 422, 503),
)
async def room_map(
    room_id: RoomId,
    registry: RegistryDep,
    cache: CacheDep,
    pictures: PicturesDep,
    _role: AnyRole,
    heatmap: Annotated[
        Literal["auto", "coverage", "crlb", "none"],
        Query(
            description="`coverage`: LEDs in the receiver's field of view per point; `crlb`: "
            "single-target Cramér-Rao bound (cm) at `snr_db`; `none`: plan only; `auto`: "
            "`coverage` unless it is the same everywhere (one flat colour), then `crlb`"
        ),
    ] = "auto",
    fingerprint_version: Annotated[
        int | None,
        Query(ge=1, le=MAX_VERSION, description="whose layout to draw; default: the current one"),
    ] = None,
    snr_db: Annotated[float, Query(ge=-20, le=100, description="SNR of the `crlb` map, dB")] = 30.0,
    width_px: Annotated[int, Query(ge=200, le=4000, description="width, pixels")] = 800,
    if_none_match: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> Response:
    """The room as a PNG: LEDs (index, beam footprint), the grid, and a heat map.

    Cached per (room, fingerprint version, options): a new version draws anew. Answers 304
    to a matching `If-None-Match`.
    """
    plan = await run_in_threadpool(
        lambda: draw_room_map(
            registry,
            cache,
            pictures,
            room_id=room_id,
            fingerprint_version=fingerprint_version,
            heatmap=heatmap,
            snr_db=snr_db,
            width_px=width_px,
        )
    )
    etag = plan.picture.etag
    headers = _headers(etag, plan.fingerprint_version, pinned=fingerprint_version is not None)
    if if_none_match is not None and etag in {t.strip() for t in if_none_match.split(",")}:
        return Response(status_code=304, headers=headers)
    return Response(content=plan.picture.png, media_type="image/png", headers=headers)


@router.post(
    "/localization.png",
    summary="Draw estimates against the truth",
    response_class=Response,
    responses=_PNG | problem_responses(401, 404, 409, 413, 422, 503),
)
async def localization_picture(
    room_id: RoomId, body: LocalizationPlot, registry: RegistryDep, cache: CacheDep, _role: AnyRole
) -> Response:
    """Estimated positions (blue crosses, labelled with `terminal_id`) and, when sent, the
    true ones (red dots), each truth joined to its matched estimate, like the paper's Fig. 3.

    Paste a localization's `estimates` and a simulation's `truth` as they are (their other
    fields are ignored).
    """
    drawn = await run_in_threadpool(
        lambda: draw_localization(registry, cache, room_id=room_id, body=body)
    )
    headers = {"Cache-Control": "no-store"}
    if drawn.fingerprint_version is not None:
        headers["X-Fingerprint-Version"] = str(drawn.fingerprint_version)
    return Response(content=drawn.png, media_type="image/png", headers=headers)
