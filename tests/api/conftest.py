"""API test fixtures: an app per test on its own data dir and SQLite registry."""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.main import create_app
from app.settings import Settings

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
    "make_settings",
    "wait_for_job",
    "wait_for_room",
]

ADMIN_KEY = "admin-test-key"
TERMINAL_KEY = "term-key"
ADMIN = {"X-API-Key": ADMIN_KEY}
TERMINAL = {"X-API-Key": TERMINAL_KEY}
BUILD_TIMEOUT_S = 90.0


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


def wait_for_room(
    client: TestClient, room_id: str, timeout_s: float = BUILD_TIMEOUT_S
) -> dict[str, Any]:
    """Poll the room until its fingerprint is ready (fail on `failed` or timeout)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        room: dict[str, Any] = client.get(f"/v1/rooms/{room_id}", headers=TERMINAL).json()
        status = room["fingerprint"]["status"]
        assert status != "failed", room
        if status == "ready":
            return room
        time.sleep(0.1)
    raise AssertionError(f"room {room_id} not ready after {timeout_s} s")


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


def wait_for_job(
    client: TestClient, job_id: str, timeout_s: float = BUILD_TIMEOUT_S
) -> dict[str, Any]:
    """Poll a job until it succeeded (fail on `failed` or timeout) and return it."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job: dict[str, Any] = client.get(f"/v1/jobs/{job_id}", headers=TERMINAL).json()
        assert job["status"] != "failed", job
        if job["status"] == "succeeded":
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} not done after {timeout_s} s")
