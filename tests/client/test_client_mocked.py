"""VLPClient over httpx.MockTransport: endpoints other branches add, and failure paths.

The epoch, calibration and map endpoints are coded against their agreed shapes
(openapi/openapi.json); a fake server checks what the client sends.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import httpx
import pytest

from app.client import (
    APIError,
    ClientError,
    Epoch,
    InvalidRequest,
    JobFailed,
    JobTimeout,
    ServerError,
    TransportError,
    VLPClient,
)
from app.schemas.localize import localize_example

Handler = Callable[[httpx.Request], httpx.Response]
ROOM = "r1"


def _job(status: str, *, progress: float = 1.0, **extra: Any) -> dict[str, Any]:
    return {
        "id": "j1",
        "kind": "calibrate",
        "room_id": ROOM,
        "status": status,
        "progress": progress,
        "error": extra.pop("error", None),
        "created_at": "2026-11-22T10:00:00Z",
        "started_at": None,
        "finished_at": None,
        "result": extra.pop("result", None),
    }


def _client(handler: Handler) -> VLPClient:
    return VLPClient("http://vlp.test", api_key="k", transport=httpx.MockTransport(handler))


def _localization() -> dict[str, Any]:
    return {
        "room_id": ROOM,
        "fingerprint_version": 1,
        "model": "correlation",
        "solver": "gridless",
        "targets": 1,
        "estimates": [{"x": 1.0, "y": 2.0, "grid_index": 45, "weight": 1.0, "terminal_id": "t7"}],
        "residual_norm": 0.0,
        "noise_power": 0.0,
        "elapsed_ms": 1.0,
    }


def test_epoch_round_trip_sends_the_agreed_bodies() -> None:
    sent: list[tuple[str, str, Any]] = []
    epoch = {"id": "e1", "room_id": ROOM, "status": "open", "terminals": 0, "expires_at": None}

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.headers["X-API-Key"] == "k"
        body = json.loads(request.content) if request.content else None
        sent.append((request.method, request.url.path, body))
        if request.url.path.endswith("/measurements"):
            return httpx.Response(202, json={"terminals": 1})
        if request.url.path.endswith("/solve"):
            return httpx.Response(
                200,
                json={**epoch, "status": "solved", "terminals": 1, "localization": _localization()},
            )
        return httpx.Response(201 if request.method == "POST" else 200, json=epoch)

    with _client(handler) as vlp:
        opened = vlp.create_epoch(ROOM, min_terminals=1, window_s=5.0)
        vlp.post_epoch_measurement(ROOM, "e1", terminal_id="t7", amplitudes=[0.1] * 16)
        vlp.post_epoch_measurement(
            ROOM, "e1", terminal_id="t8", amplitudes=[None, *[0.1] * 15], detection_floor=0.05
        )
        solved = vlp.solve_epoch(ROOM, "e1")
        again = vlp.get_epoch(ROOM, "e1")
    assert isinstance(opened, Epoch) and opened.status == "open" and again.id == "e1"
    assert solved.localization is not None
    assert solved.localization.estimates[0].terminal_id == "t7"
    assert sent[:4] == [
        ("POST", f"/v1/rooms/{ROOM}/epochs", {"min_terminals": 1, "window_s": 5.0}),
        (
            "POST",
            f"/v1/rooms/{ROOM}/epochs/e1/measurements",
            {"terminal_id": "t7", "amplitudes": [0.1] * 16},
        ),
        (
            "POST",
            f"/v1/rooms/{ROOM}/epochs/e1/measurements",
            {"terminal_id": "t8", "amplitudes": [None, *[0.1] * 15], "detection_floor": 0.05},
        ),
        ("POST", f"/v1/rooms/{ROOM}/epochs/e1/solve", None),
    ]


def test_calibrate_waits_for_the_job_and_reads_the_report() -> None:
    polls = iter([_job("queued", progress=0.0), _job("running", progress=0.5)])
    survey = [{"x": 1.0, "y": 1.0, "led": 0, "amplitude": 2e-5}]

    def handler(request: httpx.Request) -> httpx.Response:
        path = request.url.path
        if request.method == "POST":
            assert path == f"/v1/rooms/{ROOM}/calibrations"
            assert json.loads(request.content) == {"survey": survey, "masked_leds": [3]}
            return httpx.Response(202, json=_job("queued", progress=0.0))
        if path == "/v1/jobs/j1":
            done = _job("succeeded", result={"calibration_id": "c1"})
            return httpx.Response(200, json=next(polls, done))
        assert path == f"/v1/rooms/{ROOM}/calibrations/c1"
        return httpx.Response(200, json={"id": "c1", "rms_error": 0.01})

    progress: list[float] = []
    with _client(handler) as vlp:
        job = vlp.calibrate(ROOM, survey, masked_leds=[3])
        done = vlp.wait_for_job(job.id, poll_s=0, on_progress=lambda j: progress.append(j.progress))
        report = vlp.get_calibration(ROOM, str((done.result or {})["calibration_id"]))
    assert progress == [0.0, 0.5, 1.0]
    assert report == {"id": "c1", "rms_error": 0.01}


def test_room_map_is_png_bytes() -> None:
    png = b"\x89PNG\r\n\x1a\n" + b"\x00" * 16

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == f"/v1/rooms/{ROOM}/map.png"
        return httpx.Response(200, content=png, headers={"Content-Type": "image/png"})

    with _client(handler) as vlp:
        assert vlp.room_map_png(ROOM) == png


def test_sparse_gains_come_from_the_npz_path() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == f"/v1/rooms/{ROOM}/fingerprints/3/H.npz"
        return httpx.Response(200, content=b"PK\x03\x04")

    with _client(handler) as vlp:
        assert vlp.download_sparse_gains(ROOM, 3) == b"PK\x03\x04"


def test_a_failed_job_raises_with_its_error() -> None:
    failing = _job("failed", error="survey has no row for LED 4")
    with (
        _client(lambda _request: httpx.Response(200, json=failing)) as vlp,
        pytest.raises(JobFailed, match="no row for LED 4") as failed,
    ):
        vlp.wait_for_job("j1", poll_s=0)
    assert failed.value.job.status == "failed"


def test_a_job_that_never_finishes_times_out() -> None:
    running = _job("running", progress=0.3)
    with (
        _client(lambda _request: httpx.Response(200, json=running)) as vlp,
        pytest.raises(JobTimeout, match="still running"),
    ):
        vlp.wait_for_job("j1", timeout_s=0, poll_s=0)


def test_no_answer_is_a_transport_error() -> None:
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    def slow(request: httpx.Request) -> httpx.Response:
        raise httpx.ReadTimeout("timed out", request=request)

    with _client(refuse) as vlp:
        assert not vlp.is_ready()
    with _client(refuse) as vlp, pytest.raises(TransportError, match="refused") as refused:
        vlp.list_rooms()
    assert isinstance(refused.value.__cause__, httpx.ConnectError)
    with _client(slow) as vlp, pytest.raises(TransportError, match="timed out"):
        vlp.localize(ROOM, localize_example())


def test_answers_that_are_not_problems_still_map_by_status() -> None:
    with (
        _client(lambda _request: httpx.Response(502, text="<html>bad gateway</html>")) as vlp,
        pytest.raises(ServerError) as server,
    ):
        vlp.list_rooms()
    assert server.value.status == 502 and server.value.title == "Bad Gateway"
    assert server.value.errors == [] and server.value.problem == {}
    with (
        _client(lambda _request: httpx.Response(418, json={"title": "Teapot"})) as vlp,
        pytest.raises(APIError) as other,
    ):
        vlp.list_rooms()
    assert type(other.value) is APIError and other.value.title == "Teapot"


@pytest.mark.parametrize("status", [400, 413, 415, 422], ids=str)
def test_bad_requests_carry_their_field_errors(status: int) -> None:
    problem = {
        "type": "urn:vlp:problem:validation",
        "title": "Validation failed",
        "status": status,
        "detail": "body.targets: must be at least 1",
        "instance": f"/v1/rooms/{ROOM}/simulate",
        "errors": [{"field": "body.targets", "message": "must be at least 1"}],
        "request_id": "abc",
    }
    answer = httpx.Response(status, json=problem, headers={"Content-Type": "application/json"})
    with _client(lambda _request: answer) as vlp, pytest.raises(InvalidRequest) as invalid:
        vlp.simulate(ROOM, targets=0)
    error = invalid.value
    assert isinstance(error, ClientError)
    assert (error.status, error.type, error.request_id) == (status, problem["type"], "abc")
    assert [(e.field, e.message) for e in error.errors] == [("body.targets", "must be at least 1")]
