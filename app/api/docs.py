"""Swagger UI and ReDoc served from the installed ``fastapi_offline`` assets (no internet)."""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["STATIC_DOCS_URL", "install_docs"]

STATIC_DOCS_URL = "/static-docs"
_ASSETS = Path(fastapi_offline.__file__).parent / "static"


def install_docs(app: FastAPI, *, openapi_url: str = "/openapi.json") -> None:
    """Mount the assets and add ``/docs`` (Swagger UI), ``/redoc`` and ``/`` (to ``/docs``)."""
    app.mount(STATIC_DOCS_URL, StaticFiles(directory=_ASSETS), name="static-docs")
    redirect_url = "/docs/oauth2-redirect"

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=redirect_url,
            swagger_js_url=f"{STATIC_DOCS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{STATIC_DOCS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{STATIC_DOCS_URL}/favicon.png",
            swagger_ui_parameters={"persistAuthorization": True, "tryItOutEnabled": True},
        )

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        # A person who opens the bare address wants the docs; it shows no data, so no key.
        return RedirectResponse("/docs", status_code=307)

    @app.get(redirect_url, include_in_schema=False)
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=openapi_url,
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{STATIC_DOCS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{STATIC_DOCS_URL}/favicon.png",
            with_google_fonts=False,
        )
