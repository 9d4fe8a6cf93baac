"""Simulation: a ready-to-send measurement for given or random terminals, with the truth."""

from __future__ import annotations

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app.schemas import Simulation, SimulationRequest
from app.services.simulation import simulate as simulate_request

from .deps import AnyRole, CacheDep, RoomId
from .errors import problem_responses

__all__ = ["router"]

router = APIRouter(prefix="/v1/rooms", tags=["localization"])


@router.post(
    "/{room_id}/simulate",
    summary="Simulate a measurement with its ground truth",
    responses=problem_responses(401, 404, 409, 413, 422, 503),
    # The measurement carries only the fields it was built with (as a client sends it).
    response_model_exclude_unset=True,
)
async def simulate(
    room_id: RoomId, body: SimulationRequest, cache: CacheDep, _role: AnyRole
) -> Simulation:
    """Place `targets` random terminals (or the given `positions`), add Gaussian noise at
    `snr_db` (default 30 dB; or an explicit `noise_std`) and answer with a `measurement`
    you can send unchanged to `POST /v1/rooms/{room_id}/localize`, plus the truth.
    """
    return await run_in_threadpool(simulate_request, cache, room_id=room_id, body=body)
