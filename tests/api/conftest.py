"""API test fixtures: an app per test on its own data dir and SQLite registry."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.main import create_app
from app.settings import Settings
from tests.waiting import wait_for

with warnings.catch_warnings():
    # starlette prefers httpx2 for its test client; the suite's httpx works the same.
    warnings.filterwarnings("ignore", message=r"Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

__all__ = [
    "ADMIN",
    "ADMIN_KEY",
    "TERMINAL",
    "TERMINAL_KEY",
    "TestClient",
    "assert_problem",
    "make_settings",
    "small_room",
    "wait_for_job",
    "wait_for_room",
]

ADMIN_KEY = "admin-test-key-0123456789"
TERMINAL_KEY = "terminal-test-key-0123456789"
ADMIN = {"X-API-Key": ADMIN_KEY}
TERMINAL = {"X-API-Key": TERMINAL_KEY}
BUILD_TIMEOUT_S = 120.0  # a safety timeout


def make_settings(data_dir: Path, **overrides: Any) -> Settings:
    """Settings for one test app: known keys, no demo room, no workers unless asked."""
    values: dict[str, Any] = {
        "data_dir": data_dir,
        "database_url": None,
        "admin_keys": ADMIN_KEY,
        "terminal_keys": TERMINAL_KEY,
        "embedded_workers": 0,
        "demo": False,
        "version_check_seconds": 0,
    }
    values.update(overrides)
    return Settings(**values)


def small_room(name: str = "Small room", **changes: Any) -> dict[str, Any]:
    """A 2 x 1 m room with two LEDs (defaults left out on purpose)."""
    body: dict[str, Any] = {
        "name": name,
        "room": {"length": 2.0, "width": 1.0, "height": 2.5},
        "grid": {"step": 0.25, "receiver_height": 0.8},
        "leds": [{"x": 0.5, "y": 0.5}, {"x": 1.5, "y": 0.5, "pilot_amplitude": 2.0}],
    }
    body.update(changes)
    return body


def assert_problem(response: Any, status: int, fields: list[str] | None = None) -> dict[str, Any]:
    """The response is a problem of ``status`` naming exactly ``fields`` (when given)."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/problem+json"
    problem: dict[str, Any] = response.json()
    assert {"type", "title", "status", "detail", "instance"} <= problem.keys()
    assert problem["status"] == status
    if fields is not None:
        assert sorted(error["field"] for error in problem["errors"]) == sorted(fields)
    return problem


def wait_for_room(
    client: TestClient, room_id: str, timeout_s: float = BUILD_TIMEOUT_S
) -> dict[str, Any]:
    """Poll the room until its fingerprint is ready (fail at once on `failed`)."""
    room: dict[str, Any] = {}

    def ready() -> bool:
        room.update(client.get(f"/v1/rooms/{room_id}", headers=TERMINAL).json())
        assert room["fingerprint"]["status"] != "failed", room
        return bool(room["fingerprint"]["status"] == "ready")

    wait_for(ready, f"room {room_id} to be ready", timeout_s)
    return room


def wait_for_job(
    client: TestClient, job_id: str, timeout_s: float = BUILD_TIMEOUT_S
) -> dict[str, Any]:
    """Poll a job until it succeeded (fail at once on `failed`) and return it."""
    job: dict[str, Any] = {}

    def succeeded() -> bool:
        job.update(client.get(f"/v1/jobs/{job_id}", headers=TERMINAL).json())
        assert job["status"] != "failed", job
        return bool(job["status"] == "succeeded")

    wait_for(succeeded, f"job {job_id} to succeed", timeout_s)
    return job


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    """An app with no workers and no demo room (rooms stay `pending`)."""
    with TestClient(create_app(make_settings(tmp_path))) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def ready_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str]]:
    """An app whose demo (paper) room has a ready fingerprint; shared read-only per module."""
    data_dir = tmp_path_factory.mktemp("ready")
    settings = make_settings(data_dir, demo=True, embedded_workers=1)
    with TestClient(create_app(settings)) as test_client:
        rooms = test_client.get("/v1/rooms", headers=ADMIN).json()["items"]
        assert len(rooms) == 1
        wait_for_room(test_client, rooms[0]["id"])
        yield test_client, rooms[0]["id"]


@pytest.fixture(scope="module")
def worker_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """An app with one embedded build worker and no rooms; tests create (and change) their own."""
    settings = make_settings(tmp_path_factory.mktemp("worker"), embedded_workers=1)
    with TestClient(create_app(settings)) as test_client:
        yield test_client
