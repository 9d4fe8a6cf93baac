"""Every error is application/problem+json; body limit; request ids; no stack traces."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.main import create_app

from .conftest import ADMIN, TestClient, assert_problem, make_settings, small_room


def test_unknown_route_is_problem_404(client: TestClient) -> None:
    problem = assert_problem(client.get("/v1/nowhere"), 404)
    assert problem["instance"] == "/v1/nowhere"


def test_wrong_method_is_problem_405(client: TestClient) -> None:
    response = client.patch("/v1/rooms", headers=ADMIN)
    assert_problem(response, 405)
    assert "GET" in response.headers["allow"]


def test_unhandled_exception_is_problem_500_without_trace(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    app = create_app(make_settings(tmp_path))

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("secret internals: SELECT * FROM api_keys")

    with caplog.at_level(logging.ERROR, logger="app.errors"), TestClient(app) as client:
        response = client.get("/boom", headers={"X-Request-ID": "req-123"})
    problem = assert_problem(response, 500)
    assert "secret" not in response.text and "Traceback" not in response.text
    assert problem["request_id"] == "req-123"
    assert response.headers["x-request-id"] == "req-123"
    # Logged server-side with the request id and the trace.
    record = next(r for r in caplog.records if r.name == "app.errors")
    assert getattr(record, "request_id", None) == "req-123"
    assert record.exc_info is not None and "secret internals" in str(record.exc_info[1])


def test_request_id_is_generated_when_missing_or_unsafe(client: TestClient) -> None:
    first = client.get("/healthz").headers["x-request-id"]
    second = client.get("/healthz").headers["x-request-id"]
    assert first != second and len(first) == 32
    unsafe = client.get("/healthz", headers={"X-Request-ID": "bad id\twith spaces"})
    assert unsafe.headers["x-request-id"] != "bad id\twith spaces"


@pytest.fixture
def small_limit_client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(make_settings(tmp_path, max_body_bytes=2048))) as client:
        yield client


def test_body_over_limit_by_content_length_is_413(small_limit_client: TestClient) -> None:
    body = json.dumps(small_room(name="x" * 3000)).encode()
    response = small_limit_client.post(
        "/v1/rooms", content=body, headers={**ADMIN, "Content-Type": "application/json"}
    )
    problem = assert_problem(response, 413)
    assert "2048" in problem["detail"]


def test_streamed_body_over_limit_is_413(small_limit_client: TestClient) -> None:
    def chunks() -> Iterator[bytes]:
        for _ in range(10):
            yield b" " * 500

    # A generator body is sent chunked, with no Content-Length.
    response = small_limit_client.post(
        "/v1/rooms", content=chunks(), headers={**ADMIN, "Content-Type": "application/json"}
    )
    assert "content-length" not in response.request.headers
    assert_problem(response, 413)
    assert small_limit_client.get("/v1/rooms", headers=ADMIN).json()["items"] == []


def test_body_under_limit_passes(small_limit_client: TestClient) -> None:
    response = small_limit_client.post("/v1/rooms", json=small_room(), headers=ADMIN)
    assert response.status_code == 201


@pytest.mark.parametrize(
    "content, content_type",
    [
        (b"{not json", "application/json"),
        (b"", "application/json"),
        (b"[1, 2]", "application/json"),
    ],
    ids=["broken-json", "empty", "array"],
)
def test_non_json_body_is_problem_422(
    client: TestClient, content: bytes, content_type: str
) -> None:
    response = client.post(
        "/v1/rooms", content=content, headers={**ADMIN, "Content-Type": content_type}
    )
    problem = assert_problem(response, 422)
    assert problem["errors"] and all(e["field"].startswith("body") for e in problem["errors"])
    # A form body is a 415 (not declared JSON): tests/api/test_small_items.py.


def test_every_error_family_is_exported_and_mapped() -> None:
    import app.errors
    import app.registry.errors
    import app.vlp.errors
    from app.api.errors import _registry_status

    for module in (app.registry.errors, app.vlp.errors):
        for name in module.__all__:
            assert getattr(app.errors, name) is getattr(module, name), name
    expected = {
        "RoomNotFound": 404,
        "JobNotFound": 404,
        "FingerprintNotFound": 404,
        "MatrixNotFound": 409,
        "EpochNotFound": 404,
        "TrackNotFound": 404,
        "RecordNotFound": 404,
        "StateConflict": 409,
        "EpochClosed": 409,
        "EpochFull": 409,
        "PreconditionFailed": 412,
        "FingerprintNotReady": 409,
        "InvalidCursor": 422,
        "CorruptMatrix": 503,
        "RegistryUnavailable": 503,
        "RegistryError": 500,
    }
    assert set(expected) == set(app.registry.errors.__all__)
    for name, status in expected.items():
        error = getattr(app.registry.errors, name)("message")
        assert _registry_status(error)[0] == status, name


def test_science_errors_are_input_problems_except_a_failed_solver() -> None:
    from app.api.errors import ProblemKind, _science_status
    from app.errors import GeometryError, MeasurementError, SolverError, SolverFailed

    assert _science_status(SolverFailed("no answer")) == (503, ProblemKind.SOLVER_FAILED)
    for error in (GeometryError, MeasurementError, SolverError):
        assert _science_status(error("bad")) == (422, ProblemKind.VALIDATION)


@pytest.mark.parametrize(
    "field, location",
    [("leds[3].z", "body.leds.3.z"), ("correlation", "body.correlation"), (None, "body")],
)
def test_science_fields_become_request_locations(field: str | None, location: str) -> None:
    from app.api.errors import field_location

    assert field_location(field) == location
