"""Pictures: the room plan (``map.png``) and estimates against the truth (``localization.png``).

The plan is drawn from the layout of a fingerprint version (the current one by default, so
a calibrated room shows its fitted beams and no masked LEDs), or from the room's layout
while no fingerprint is ready. Rendered PNGs are kept in the process's
:class:`~app.api.picture_cache.PictureCache`, keyed by room, version and options.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Header, Query, Response
from starlette.concurrency import run_in_threadpool

from app.pictures import localization_png, room_map_png
from app.registry import Registry
from app.registry.errors import FingerprintNotReady
from app.schemas import LocalizationPlot
from app.schemas.common import MAX_VERSION
from app.services.fingerprint_cache import FingerprintCache
from app.vlp.layout import Layout, layout_from_mapping

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


def _layout_for(
    room_id: str, version: int | None, registry: Registry, cache: FingerprintCache
) -> tuple[Layout, int | None, int]:
    """``(layout, fingerprint version or None, room layout version)`` to draw."""
    room = registry.get_room(room_id=room_id)
    if version is None:
        try:
            version = cache.current_version(room_id)
        except FingerprintNotReady:
            return layout_from_mapping(room.layout), None, room.layout_version
    else:
        registry.get_fingerprint(room_id=room_id, version=version)  # 404 when unknown
    return cache.fingerprint(room_id, version).layout, version, room.layout_version


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
    layout, version, layout_version = await run_in_threadpool(
        _layout_for, room_id, fingerprint_version, registry, cache
    )
    source = ("fingerprint", version) if version is not None else ("layout", layout_version)
    key = (room_id, *source, heatmap, float(snr_db), width_px)
    picture = pictures.get(key)
    if picture is None:
        png = await run_in_threadpool(
            lambda: room_map_png(layout, heatmap=heatmap, snr_db=snr_db, width_px=width_px)
        )
        picture = pictures.put(key, png)
    headers = _headers(picture.etag, version, pinned=fingerprint_version is not None)
    if if_none_match is not None and picture.etag in {t.strip() for t in if_none_match.split(",")}:
        return Response(status_code=304, headers=headers)
    return Response(content=picture.png, media_type="image/png", headers=headers)


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
    layout, version, _ = await run_in_threadpool(
        _layout_for, room_id, body.fingerprint_version, registry, cache
    )
    estimates = np.array([[p.x, p.y] for p in body.estimates], dtype=np.float64).reshape(-1, 2)
    truth = (
        None
        if body.truth is None
        else np.array([[p.x, p.y] for p in body.truth], dtype=np.float64).reshape(-1, 2)
    )
    labels = [p.terminal_id for p in body.estimates]
    png = await run_in_threadpool(
        lambda: localization_png(
            layout,
            estimates,
            truth,
            labels=labels if any(labels) else None,
            width_px=body.width_px,
            title=body.title,
        )
    )
    headers = {"Cache-Control": "no-store"}
    if version is not None:
        headers["X-Fingerprint-Version"] = str(version)
    return Response(content=png, media_type="image/png", headers=headers)
