"""The live view: ``GET /view`` and its script and style, shipped in the package (``app/view``).

Plain HTML, JavaScript and SVG, nothing built at run time and nothing from another origin:
every answer carries ``Content-Security-Policy: default-src 'self'``. The page needs no key to
load; it asks for one and sends it as ``X-API-Key`` with each API call it makes.
"""

from __future__ import annotations

from importlib import resources
from typing import Annotated

from fastapi import APIRouter, Path
from fastapi.responses import Response

from .errors import ApiProblem, ProblemKind

__all__ = ["CONTENT_SECURITY_POLICY", "router"]

CONTENT_SECURITY_POLICY = "default-src 'self'"
_FILES = {
    "view.js": "text/javascript; charset=utf-8",
    "view.css": "text/css; charset=utf-8",
    "favicon.svg": "image/svg+xml",
}
_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}

router = APIRouter(include_in_schema=False)


def _asset(name: str) -> bytes:
    return resources.files("app.view").joinpath(name).read_bytes()


@router.get("/view")
def view_page() -> Response:
    """The live view's page."""
    return Response(_asset("index.html"), media_type="text/html; charset=utf-8", headers=_HEADERS)


@router.get("/view/{name}")
def view_asset(name: Annotated[str, Path(max_length=32)]) -> Response:
    """The page's script, style and icon (nothing else is served from here)."""
    if name not in _FILES:
        raise ApiProblem(404, f"the view has no file {name!r}", kind=ProblemKind.NOT_FOUND)
    return Response(_asset(name), media_type=_FILES[name], headers=_HEADERS)
