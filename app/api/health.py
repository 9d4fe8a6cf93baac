"""Operations: liveness, readiness and Prometheus metrics (no key needed)."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool

from .deps import MetricsDep, RegistryDep
from .errors import ApiProblem, ProblemKind, problem_responses

__all__ = ["router"]

router = APIRouter(tags=["operations"])


class Health(BaseModel):
    """The process answers."""

    status: Literal["ok"] = "ok"


class Readiness(BaseModel):
    """The registry is reachable and its schema is current."""

    status: Literal["ready"] = "ready"


@router.get("/healthz", summary="Liveness")
def healthz() -> Health:
    """Always `ok` while the process serves requests."""
    return Health()


def _check_ready(registry: RegistryDep) -> None:
    registry.ping()
    if not registry.migrations_current():
        raise ApiProblem(
            503,
            "the registry schema is not at the current migration",
            kind=ProblemKind.NOT_READY,
            headers={"Retry-After": "5"},
        )


@router.get("/readyz", summary="Readiness", responses=problem_responses(503))
async def readyz(registry: RegistryDep) -> Readiness:
    """`ready` when the registry answers and its schema is migrated; 503 otherwise."""
    await run_in_threadpool(_check_ready, registry)
    return Readiness()


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={
        200: {
            "description": "Prometheus text format",
            "content": {"text/plain": {"schema": {"type": "string"}}},
        }
    },
)
def metrics(metrics: MetricsDep) -> Response:
    """Requests and latency by route, localize latency by solver, jobs by status, cache hits."""
    return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)
