"""Configurable limits (``VLP_MAX_*``): body size, LEDs, grid points, builds per room."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.main import create_app
from app.settings import Settings

from .conftest import ADMIN, ADMIN_KEY, TERMINAL_KEY, TestClient, assert_problem, small_room


@pytest.fixture
def env_limited_client(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> TestClient:
    """An app whose limits come from the environment only."""
    for name, value in {
        "VLP_DATA_DIR": str(tmp_path),
        "VLP_ADMIN_KEYS": ADMIN_KEY,
        "VLP_TERMINAL_KEYS": TERMINAL_KEY,
        "VLP_EMBEDDED_WORKERS": "0",
        "VLP_DEMO": "0",
        "VLP_MAX_BODY_BYTES": "4096",
        "VLP_MAX_LEDS": "2",
        "VLP_MAX_GRID_POINTS": "32",
        "VLP_MAX_CONCURRENT_BUILDS_PER_ROOM": "2",
    }.items():
        monkeypatch.setenv(name, value)
    return TestClient(create_app(Settings()))


def test_limits_are_read_from_the_environment(env_limited_client: TestClient) -> None:
    with env_limited_client as client:
        settings: Settings = client.app.state.settings  # type: ignore[attr-defined]
        assert (settings.max_body_bytes, settings.max_leds, settings.max_grid_points) == (
            4096,
            2,
            32,
        )
        assert settings.max_concurrent_builds_per_room == 2
        # small_room(): 2 LEDs, 8 x 4 = 32 grid points, exactly at the limits.
        assert client.post("/v1/rooms", json=small_room(), headers=ADMIN).status_code == 201
        three_leds = small_room(leds=[{"x": 0.5, "y": 0.5}] * 3)
        problem = assert_problem(
            client.post("/v1/rooms", json=three_leds, headers=ADMIN), 422, ["body.leds"]
        )
        assert "at most 2 LEDs" in problem["detail"]
        finer = small_room(grid={"step": 0.125, "receiver_height": 0.8})  # 128 points
        problem = assert_problem(
            client.post("/v1/rooms", json=finer, headers=ADMIN), 422, ["body.grid.step"]
        )
        assert "at most 32" in problem["detail"]
        big = json.dumps(small_room(name="x" * 5000)).encode()
        response = client.post(
            "/v1/rooms", content=big, headers={**ADMIN, "Content-Type": "application/json"}
        )
        assert "4096" in assert_problem(response, 413)["detail"]
        assert len(client.get("/v1/rooms", headers=ADMIN).json()["items"]) == 1


@pytest.mark.parametrize(
    "name, value",
    [("VLP_MAX_LEDS", "0"), ("VLP_MAX_GRID_POINTS", "-1"), ("VLP_MAX_BODY_BYTES", "10")],
)
def test_nonsense_limits_are_refused_at_start(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str
) -> None:
    monkeypatch.setenv(name, value)
    with pytest.raises(ValueError, match=name.removeprefix("VLP_").lower()):
        Settings()


def test_rebuild_requests_coalesce_into_one_queued_job(client: TestClient) -> None:
    """A rebuild asked for while one is queued joins it (202, same job), even after the
    layout changed (the queued job builds the newest layout): one queued build per room."""
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    path = f"/v1/rooms/{room['id']}"
    first_job = room["fingerprint"]["job_id"]
    jobs = {client.post(f"{path}/fingerprints", headers=ADMIN).json()["id"] for _ in range(5)}
    assert jobs == {first_job}
    etag = client.get(path, headers=ADMIN).headers["etag"]
    replaced = client.put(path, json=small_room("New"), headers={**ADMIN, "If-Match": etag})
    assert replaced.json()["fingerprint"]["job_id"] == first_job
    job = client.post(f"{path}/fingerprints", headers=ADMIN)
    assert job.status_code == 202 and job.json()["id"] == first_job
    assert job.json()["layout_version"] == 2
    counts = client.app.state.registry.count_jobs_by_status()  # type: ignore[attr-defined]
    assert counts["queued"] == 1 and counts["running"] == 0
