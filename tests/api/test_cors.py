"""CORS from ``VLP_CORS_ORIGINS``: a real preflight, and the headers of the actual request."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from app.main import create_app

from .conftest import ADMIN, TestClient, make_settings

ALLOWED = "https://app.example.org"
PREFLIGHT = {
    "Access-Control-Request-Method": "PUT",
    "Access-Control-Request-Headers": "x-api-key, if-match, content-type",
}


@pytest.fixture
def cors_client(tmp_path: Path) -> Iterator[TestClient]:
    settings = make_settings(tmp_path, cors_origins=f"{ALLOWED}, https://other.example.org")
    with TestClient(create_app(settings)) as test_client:
        yield test_client


def test_preflight_from_an_allowed_origin(cors_client: TestClient) -> None:
    answer = cors_client.options("/v1/rooms/abc", headers={"Origin": ALLOWED, **PREFLIGHT})
    assert answer.status_code == 200, answer.text
    assert answer.headers["access-control-allow-origin"] == ALLOWED
    assert "PUT" in answer.headers["access-control-allow-methods"]
    allowed = answer.headers["access-control-allow-headers"].lower()
    assert {"x-api-key", "if-match", "content-type"} <= {h.strip() for h in allowed.split(",")}


def test_preflight_from_another_origin_gets_no_cors_headers(cors_client: TestClient) -> None:
    answer = cors_client.options(
        "/v1/rooms/abc", headers={"Origin": "https://evil.example.com", **PREFLIGHT}
    )
    assert answer.status_code == 400
    assert "access-control-allow-origin" not in answer.headers


def test_actual_request_exposes_etag_location_retry_after(cors_client: TestClient) -> None:
    answer = cors_client.get("/v1/rooms", headers={"Origin": ALLOWED, **ADMIN})
    assert answer.status_code == 200
    assert answer.headers["access-control-allow-origin"] == ALLOWED
    exposed = {
        h.strip().lower() for h in answer.headers["access-control-expose-headers"].split(",")
    }
    assert {"etag", "location", "retry-after"} <= exposed
    other = cors_client.get("/v1/rooms", headers={"Origin": "https://evil.example.com", **ADMIN})
    assert "access-control-allow-origin" not in other.headers


def test_no_origins_configured_means_no_cors(client: TestClient) -> None:
    answer = client.options("/v1/rooms", headers={"Origin": ALLOWED, **PREFLIGHT})
    assert "access-control-allow-origin" not in answer.headers
    assert answer.status_code == 405
