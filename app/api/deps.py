"""Dependencies: the resources built in the lifespan, and the caller's role.

Handlers take them through the ``Annotated`` aliases below. They are ``async``: FastAPI runs
a plain ``def`` dependency in the thread pool, a hop that costs more than these lookups.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request, Security
from fastapi.security import APIKeyHeader
from starlette.concurrency import run_in_threadpool

from app.registry import Registry
from app.services.fingerprint_cache import FingerprintCache
from app.services.picture_cache import PictureCache
from app.settings import Settings
from app.telemetry import Metrics

from .errors import ApiProblem, ProblemKind
from .security import KeyCache, Role

__all__ = [
    "AdminRole",
    "AnyRole",
    "CacheDep",
    "JobId",
    "KeysDep",
    "MetricsDep",
    "PicturesDep",
    "RegistryDep",
    "RoomId",
    "SettingsDep",
    "api_key_header",
    "current_role",
    "require_admin",
]

api_key_header = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    scheme_name="ApiKey",
    description="an admin or terminal key (see the server's `credentials` file at first start)",
)


async def get_registry(request: Request) -> Registry:
    """The registry built in the lifespan."""
    registry: Registry = request.app.state.registry
    return registry


async def get_settings(request: Request) -> Settings:
    """The settings the app was created with."""
    settings: Settings = request.app.state.settings
    return settings


async def get_cache(request: Request) -> FingerprintCache:
    """The per-process fingerprint and solver cache."""
    cache: FingerprintCache = request.app.state.cache
    return cache


async def get_keys(request: Request) -> KeyCache:
    """This process's API key cache."""
    keys: KeyCache = request.app.state.keys
    return keys


async def get_metrics(request: Request) -> Metrics:
    """The app's Prometheus metrics."""
    metrics: Metrics = request.app.state.metrics
    return metrics


async def get_pictures(request: Request) -> PictureCache:
    """The per-process cache of rendered PNGs."""
    pictures: PictureCache = request.app.state.pictures
    return pictures


RoomId = Annotated[
    str,
    Path(
        max_length=64,
        description="the room's id (from `POST /v1/rooms` or `GET /v1/rooms`)",
        examples=["3f2c9d1e6b0a4c8e9f7d5b3a1c2e4f60"],
    ),
]
JobId = Annotated[
    str, Path(max_length=64, description="the job's id (a room's `fingerprint.job_id`)")
]
RegistryDep = Annotated[Registry, Depends(get_registry)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
CacheDep = Annotated[FingerprintCache, Depends(get_cache)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
PicturesDep = Annotated[PictureCache, Depends(get_pictures)]
KeysDep = Annotated[KeyCache, Depends(get_keys)]


async def current_role(
    request: Request,
    key: Annotated[str | None, Security(api_key_header)] = None,
) -> Role:
    """The caller's role from ``X-API-Key``; 401 when it is missing or unknown.

    A key this process has checked within the cache's TTL is answered from memory, on the
    event loop; only a registry read goes to the thread pool.
    """
    if not key:
        raise ApiProblem(
            401,
            "this endpoint needs an API key in the X-API-Key header",
            kind=ProblemKind.UNAUTHORIZED,
            headers={"WWW-Authenticate": "X-API-Key"},
        )
    keys: KeyCache = request.app.state.keys
    role = keys.fresh_role(key)
    if role is None:
        role = await run_in_threadpool(keys.role_for, key)
    if role is None:
        raise ApiProblem(
            401,
            "unknown API key",
            kind=ProblemKind.UNAUTHORIZED,
            headers={"WWW-Authenticate": "X-API-Key"},
        )
    return role


AnyRole = Annotated[Role, Depends(current_role)]


async def require_admin(role: AnyRole) -> Role:
    """403 unless the caller is an admin."""
    if role != "admin":
        raise ApiProblem(
            403,
            f"the {role} role may not do this; it needs an admin key",
            kind=ProblemKind.FORBIDDEN,
        )
    return role


AdminRole = Annotated[Role, Depends(require_admin)]
