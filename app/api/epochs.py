"""Cooperation epochs: terminals post their own amplitudes into a short window; solved once.

Create an epoch, let each terminal post its amplitudes (again replaces), and read it or call
``solve``; see :mod:`app.services.epoch_settler` for how and when windows close.
"""

from __future__ import annotations

import asyncio
import math
import time
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Body, Depends, Path, Request, Response, status
from starlette.concurrency import run_in_threadpool

from app.schemas import Epoch, EpochCreate, EpochMeasurement
from app.schemas.epochs import epoch_create_examples, epoch_measurement_examples
from app.services.epoch_settler import EpochSettler
from app.services.epochs import open_requested_epoch, post_to_epoch
from app.services.public import epoch_public

from .deps import AnyRole, RegistryDep, RoomId, SettingsDep
from .errors import problem_responses

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["epochs"])
# How often a solve request looks again while another process is solving the epoch.
_SOLVE_POLL_S = 0.05

EpochId = Annotated[
    str, Path(max_length=64, description="the epoch's id (from `POST /v1/rooms/{room_id}/epochs`)")
]


async def get_settler(request: Request) -> EpochSettler:
    """The epoch settler built in the lifespan."""
    settler: EpochSettler = request.app.state.epoch_settler
    return settler


SettlerDep = Annotated[EpochSettler, Depends(get_settler)]


@router.post(
    "/{room_id}/epochs",
    status_code=status.HTTP_201_CREATED,
    summary="Open a cooperation epoch",
    responses={
        201: {"headers": {"Location": {"schema": {"type": "string"}}}},
        **problem_responses(401, 404, 409, 413, 422, 503),
    },
)
def create_epoch(
    room_id: RoomId,
    response: Response,
    registry: RegistryDep,
    settings: SettingsDep,
    _role: AnyRole,
    body: Annotated[EpochCreate | None, Body(openapi_examples=epoch_create_examples())] = None,
) -> Epoch:
    """Open a window of `window_s` seconds that terminals join with
    `POST .../epochs/{epoch_id}/measurements`; the body may be left out (all defaults).

    The epoch uses the room's current fingerprint (409 while there is none).
    """
    body = body or EpochCreate()
    record = open_requested_epoch(
        registry, room_id=room_id, body=body, max_terminals=settings.epoch_max_terminals
    )
    response.headers["Location"] = f"/v1/rooms/{room_id}/epochs/{record.id}"
    return epoch_public(record)


@router.post(
    "/{room_id}/epochs/{epoch_id}/measurements",
    status_code=status.HTTP_202_ACCEPTED,
    summary="Post one terminal's amplitudes to an epoch",
    responses={
        202: {
            "headers": {
                "Retry-After": {
                    "schema": {"type": "integer"},
                    "description": "seconds until the window closes (read the epoch then)",
                }
            }
        },
        **problem_responses(401, 404, 409, 413, 422, 503),
    },
)
def post_epoch_measurement(
    room_id: RoomId,
    epoch_id: EpochId,
    body: Annotated[EpochMeasurement, Body(openapi_examples=epoch_measurement_examples())],
    response: Response,
    registry: RegistryDep,
    _role: AnyRole,
) -> Epoch:
    """Add (or replace) this terminal's amplitudes, one per LED of the room (the LEDs a
    calibration masked are dropped) or of the epoch's fingerprint; null for an LED it did not
    detect, as in localize's `terminals`, with its optional `detection_floor`.

    409 once the window has closed or the epoch has its maximum of terminals.
    """
    record = post_to_epoch(
        registry,
        room_id=room_id,
        epoch_id=epoch_id,
        terminal_id=body.terminal_id,
        amplitudes=body.amplitudes,
        detection_floor=body.detection_floor,
    )
    to_close_s = (record.expires_at - datetime.now(UTC)).total_seconds()
    response.headers["Retry-After"] = str(max(1, math.ceil(to_close_s)))
    return epoch_public(record)


@router.post(
    "/{room_id}/epochs/{epoch_id}/solve",
    summary="Close an epoch now and solve it",
    responses=problem_responses(401, 404, 503),
)
async def solve_epoch(
    room_id: RoomId,
    epoch_id: EpochId,
    settler: SettlerDep,
    settings: SettingsDep,
    _role: AnyRole,
) -> Epoch:
    """Close the window and solve from the terminals that posted (or `expired` when fewer
    than `min_terminals` did). A closed epoch is answered as it is; when another server
    process is solving it, this waits for its outcome (up to the solve lease).
    """
    deadline = time.monotonic() + settings.epoch_solve_lease_seconds
    while True:
        record = await run_in_threadpool(
            settler.settle, room_id=room_id, epoch_id=epoch_id, force=True
        )
        if record.status != "solving" or time.monotonic() >= deadline:
            return epoch_public(record)
        await asyncio.sleep(_SOLVE_POLL_S)


@router.get(
    "/{room_id}/epochs/{epoch_id}",
    summary="Read an epoch",
    responses=problem_responses(401, 404, 503),
)
def get_epoch(room_id: RoomId, epoch_id: EpochId, settler: SettlerDep, _role: AnyRole) -> Epoch:
    """The epoch; one whose window has passed is closed (and solved) by this read if no
    server process has done so yet."""
    return epoch_public(settler.settle(room_id=room_id, epoch_id=epoch_id, force=False))
