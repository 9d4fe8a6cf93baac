"""The FastAPI application factory.

Everything stateful (registry, workers, caches, metrics, keys) is built in the lifespan of
the app that :func:`create_app` returns; nothing at import time.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib.metadata import version as package_version
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool
from threadpoolctl import threadpool_limits

from app.api import api_router
from app.api.docs import install_docs
from app.api.errors import PROBLEM_MEDIA_TYPE, install_error_handlers, problem_example
from app.api.middleware import BodySizeLimitMiddleware, RequestContextMiddleware
from app.api.security import KeyCache, provision_keys
from app.clock import Clock, SystemClock
from app.jobs import EmbeddedWorkers
from app.jobs.epochs import EpochSweeper
from app.registry import Registry
from app.registry.seed import find_demo_room, seed_demo_room
from app.services.epoch_settler import EpochSettler
from app.services.fingerprint_cache import FingerprintCache
from app.services.picture_cache import PictureCache
from app.services.track_stream import TrackEventHub
from app.services.tracking import Tracking
from app.settings import Settings, get_settings
from app.telemetry import Metrics

__all__ = ["create_app"]

_log = logging.getLogger("app")

_DESCRIPTION = """\
Indoor multi-target **visible-light positioning** as a service: terminals measure the pilot
amplitudes of the ceiling LEDs, the service finds where they are (compressed sensing over a
fingerprint grid, after the CoCSM-VLP paper).

**Try it here:** click *Authorize* and paste a key (`X-API-Key`; the server prints its first
keys once and writes them to `VLP_DATA_DIR/credentials`). Then `GET /v1/rooms` lists the demo
room, `POST /v1/rooms/{room_id}/simulate` makes a measurement with its ground truth, and
`POST /v1/rooms/{room_id}/localize` with that `measurement` finds the targets.

Units are SI (metres; `_deg` names are degrees). Every error is `application/problem+json`.
"""

_TAGS = [
    {"name": "rooms", "description": "Room layouts: box, grid, receiver and LEDs (admin writes)"},
    {"name": "fingerprints", "description": "Channel matrices built from a layout"},
    {"name": "jobs", "description": "Background jobs: fingerprint builds and calibrations"},
    {
        "name": "calibration",
        "description": "Survey calibration: fit LED amplitudes and beams to measured "
        "amplitudes, mask dead LEDs (admin writes)",
    },
    {"name": "localization", "description": "Locate targets; simulate measurements"},
    {
        "name": "epochs",
        "description": "Cooperation windows: terminals post their own amplitudes, solved once",
    },
    {
        "name": "pictures",
        "description": "PNG pictures: the room plan with a coverage or CRLB heat map, and "
        "estimates against the truth",
    },
    {
        "name": "tracking",
        "description": "Tracks of moving terminals: their state, history, settings and a "
        "live stream (Server-Sent Events); the live view is at /view",
    },
    {"name": "keys", "description": "API keys: create, list, revoke (admin)"},
    {"name": "operations", "description": "Health, readiness, metrics (no key)"},
]


def _operation_id(route: APIRoute) -> str:
    return route.name


def _problem_validation_responses(app: FastAPI) -> None:
    """Document 422 answers as problems, not FastAPI's default ``HTTPValidationError``."""
    original = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = original()
        for operations in schema.get("paths", {}).values():
            for operation in operations.values():
                for status, answer in operation.get("responses", {}).items():
                    content = answer.get("content", {})
                    if status == "422" and PROBLEM_MEDIA_TYPE not in content:
                        answer["description"] = "invalid input; `errors` names each field"
                        content[PROBLEM_MEDIA_TYPE] = {
                            "schema": {"$ref": "#/components/schemas/Problem"},
                            "example": problem_example(422),
                        }
                    if status >= "400" and PROBLEM_MEDIA_TYPE in content:
                        content.pop("application/json", None)
        components = schema.get("components", {}).get("schemas", {})
        for name in ("HTTPValidationError", "ValidationError"):
            components.pop(name, None)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _count_jobs(app: FastAPI) -> dict[str, int] | None:
    """Jobs by status, when the registry offers ``count_jobs_by_status`` (else None)."""
    registry = getattr(app.state, "registry", None)
    counter = getattr(registry, "count_jobs_by_status", None)
    return dict(counter()) if callable(counter) else None


def _warm_up_solvers() -> None:
    """Load every solver kernel and the tracking filter's now, before serving
    (``VLP_WARM_KERNELS_AT_START``; :func:`app.vlp.solvers.warm_up` loads every row of the
    kernel table, the filter's among them); by default a process loads them when it first
    prepares a solver (:class:`app.services.fingerprint_cache.FingerprintCache`) or tracks,
    and one that never solves never imports the solvers or numba."""
    from app.vlp.solvers import warm_up

    warm_up()


def _epoch_sweeper(
    settler: EpochSettler, tracking: Tracking, settings: Settings
) -> EpochSweeper | None:
    """The started sweeper that closes passed epoch windows and ages tracks (None when
    switched off)."""
    if settings.epoch_sweep_seconds <= 0:
        return None

    def sweep() -> int:
        return settler.sweep() + tracking.sweep()

    sweeper = EpochSweeper(sweep=sweep, interval_s=settings.epoch_sweep_seconds)
    sweeper.start()
    return sweeper


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    # The one clock of this process: leases, epoch windows and version re-reads follow it.
    given: Clock | None = app.state.clock
    clock: Clock = SystemClock() if given is None else given
    with threadpool_limits(limits=1):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        registry = Registry(
            database_url=settings.resolved_database_url(),
            data_dir=settings.data_dir,
            max_build_attempts=settings.max_build_attempts,
            job_lease_seconds=settings.job_lease_seconds,
            matrix_store=settings.resolved_matrix_store(),
            clock=clock,
        )
        await run_in_threadpool(registry.migrate)
        if settings.warm_kernels_at_start:
            await run_in_threadpool(_warm_up_solvers)
        app.state.registry = registry
        credentials = await run_in_threadpool(
            lambda: provision_keys(registry=registry, settings=settings)
        )
        app.state.keys = KeyCache(registry=registry)
        demo_room = None
        if settings.demo:
            await run_in_threadpool(seed_demo_room, registry)
            demo_room = await run_in_threadpool(find_demo_room, registry)
        metrics: Metrics = app.state.metrics
        app.state.cache = FingerprintCache(
            registry=registry,
            size=settings.fingerprint_cache_size,
            max_bytes=settings.fingerprint_cache_mib * 2**20,
            version_check_seconds=settings.version_check_seconds,
            metrics=metrics,
            clock=clock,
        )
        hub = TrackEventHub(store=registry.tracks, poll_s=settings.track_stream_poll_seconds)
        hub.start()
        app.state.track_hub = hub
        app.state.tracking = Tracking(registry=registry, clock=clock, on_event=hub.published)
        app.state.epoch_settler = EpochSettler(
            registry=registry,
            cache=app.state.cache,
            metrics=metrics,
            settings=settings,
            clock=clock,
            tracking=app.state.tracking,
        )
        sweeper = _epoch_sweeper(app.state.epoch_settler, app.state.tracking, settings)
        workers = EmbeddedWorkers(registry=registry, settings=settings, clock=clock)
        if settings.embedded_workers > 0:
            workers.start()
        docs_url = f"{settings.public_url.rstrip('/')}/docs"
        demo_room_id = demo_room.id if demo_room is not None else None
        # The message itself names the docs, the demo room and the generated keys' file: it is
        # the line people read.
        _log.info(
            "service started: API docs at %s%s%s",
            docs_url,
            f", demo room {demo_room_id}" if demo_room_id else "",
            f", generated API keys in {credentials} (`source` it)" if credentials else "",
            extra={
                "data_dir": str(settings.data_dir),
                "embedded_workers": settings.embedded_workers,
                "docs_url": docs_url,
                "demo_room_id": demo_room_id,
                "credentials": None if credentials is None else str(credentials),
            },
        )
        try:
            yield
        finally:
            if sweeper is not None:
                await run_in_threadpool(sweeper.stop)
            if settings.embedded_workers > 0:
                await run_in_threadpool(workers.stop)
            await run_in_threadpool(hub.stop)
            registry.dispose()


def create_app(settings: Settings | None = None, *, clock: Clock | None = None) -> FastAPI:
    """Build the service app (the registry and workers start in its lifespan).

    ``clock`` is what "now" is for the app's leases, epoch windows and version re-reads (a
    :class:`app.clock.SystemClock` when None; tests pass an :class:`app.clock.FakeClock`).
    """
    settings = settings or get_settings()
    app = FastAPI(
        title="VLP service",
        # One version number: the package's (pyproject.toml), so clients see what runs.
        version=package_version("vlp-service"),
        # Relative: the host that served this document (any deployment, any port).
        servers=[{"url": "/", "description": "this server"}],
        description=_DESCRIPTION,
        openapi_tags=_TAGS,
        docs_url=None,
        redoc_url=None,
        lifespan=_lifespan,
        generate_unique_id_function=_operation_id,
        swagger_ui_parameters={"persistAuthorization": True},
    )
    metrics = Metrics()
    app.state.settings = settings
    app.state.clock = clock
    app.state.metrics = metrics
    app.state.pictures = PictureCache()
    metrics.watch_jobs(lambda: _count_jobs(app))
    install_error_handlers(app)
    install_docs(app)
    _problem_validation_responses(app)
    app.include_router(api_router)
    app.add_middleware(BodySizeLimitMiddleware, max_body_bytes=settings.max_body_bytes)
    app.add_middleware(RequestContextMiddleware, metrics=metrics)
    _install_cors(app, settings)
    return app


def _install_cors(app: FastAPI, settings: Settings) -> None:
    """CORS for the configured origins only (outermost, so preflights never need a key)."""
    origins = settings.cors_origin_list()
    if not origins:
        return
    app.add_middleware(
        CORSMiddleware,
        allow_origins=origins,
        allow_methods=["GET", "POST", "PUT", "DELETE", "OPTIONS"],
        allow_headers=["X-API-Key", "If-Match", "If-None-Match", "Content-Type"],
        expose_headers=["ETag", "Location", "Retry-After", "X-Request-ID"],
        max_age=600,
    )
