"""The routes' dependencies run on the event loop: FastAPI sends a plain ``def`` dependency
to the thread pool, a hop (two thread switches) per request that costs more than reading a
resource off the app's state."""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute

from app.main import create_app

from .conftest import make_settings


def _api_routes(routes: Iterable[Any]) -> Iterator[APIRoute]:
    """Every ``APIRoute`` under ``routes``, through included routers (their originals)."""
    for route in routes:
        if isinstance(route, APIRoute):
            yield route
        elif hasattr(route, "original_router"):
            yield from _api_routes(route.original_router.routes)
        elif hasattr(route, "routes"):
            yield from _api_routes(route.routes)


def _dependencies(dependant: Dependant) -> Iterator[Dependant]:
    for dependency in dependant.dependencies:
        yield dependency
        yield from _dependencies(dependency)


def _runs_on_the_loop(call: object) -> bool:
    """Whether FastAPI awaits ``call`` rather than running it in the thread pool (a
    security scheme such as ``APIKeyHeader`` is an object with an ``async __call__``)."""
    if inspect.isroutine(call):
        return inspect.iscoroutinefunction(call)
    return inspect.iscoroutinefunction(getattr(call, "__call__", None))  # noqa: B004


def test_every_dependency_of_every_route_is_awaited(tmp_path: Path) -> None:
    app = create_app(make_settings(tmp_path))
    routes = list(_api_routes(app.routes))
    assert any(route.path == "/v1/rooms/{room_id}/localize" for route in routes)
    hops = sorted(
        {
            f"{route.path}: {getattr(dependency.call, '__name__', dependency.call)}"
            for route in routes
            for dependency in _dependencies(route.dependant)
            if dependency.call is not None and not _runs_on_the_loop(dependency.call)
        }
    )
    assert hops == []
