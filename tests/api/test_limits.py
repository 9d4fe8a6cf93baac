"""Configurable limits (``VLP_MAX_*``): body size, LEDs, grid points, builds per room."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.main import create_app
from app.settings import Settings
from app.vlp.workload import localize_work

from .conftest import (
    ADMIN,
    ADMIN_KEY,
    TERMINAL,
    TERMINAL_KEY,
    TestClient,
    assert_problem,
    make_settings,
    small_room,
    wait_for_room,
)


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
    [
        ("VLP_MAX_LEDS", "0"),
        ("VLP_MAX_GRID_POINTS", "-1"),
        ("VLP_MAX_BODY_BYTES", "10"),
        ("VLP_MAX_LOCALIZE_WORK", "0"),
    ],
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


def test_localize_work_above_the_limit_is_refused_naming_the_field(tmp_path: Path) -> None:
    """VLP_MAX_LOCALIZE_WORK bounds grid points x observations x targets per request:
    small_room() has 32 grid points and 2 LEDs, so a limit of 128 admits K = 2 as power
    (32 x 2 x 2) and two terminals fitted on their own, and refuses one more of either;
    correlation has 3 observations (32 x 3 x 1 = 96 fits, K = 2 does not)."""
    settings = make_settings(tmp_path, embedded_workers=1, max_localize_work=128)
    with TestClient(create_app(settings)) as client:
        room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
        wait_for_room(client, room["id"])
        path = f"/v1/rooms/{room['id']}/localize"

        def terminals(count: int) -> list[dict[str, object]]:
            return [{"id": f"t{k}", "amplitudes": [1e-6, 2e-6]} for k in range(count)]

        admitted: list[dict[str, object]] = [
            {"power": [1e-12, 2e-12], "targets": 2},
            {"correlation": [1e-12, 0.0, 2e-12], "targets": 1},
            {"terminals": terminals(2)},
            {"terminals": terminals(3), "targets": 1, "solver": "nnls"},
        ]
        for body in admitted:
            response = client.post(path, json=body, headers=TERMINAL)
            assert response.status_code == 200, (body, response.text)
        refused: list[tuple[dict[str, object], str]] = [
            ({"power": [1e-12, 2e-12], "targets": 3}, "body.targets"),
            ({"power": [1e-12, 2e-12]}, "body.targets"),  # K unknown counts as 64
            ({"correlation": [1e-12, 0.0, 2e-12], "targets": 2}, "body.targets"),
            ({"terminals": terminals(3)}, "body.terminals"),
        ]
        for body, field in refused:
            problem = assert_problem(client.post(path, json=body, headers=TERMINAL), 422, [field])
            assert "128" in problem["detail"] and "VLP_MAX_LOCALIZE_WORK" in problem["detail"]
            assert "32 grid points" in problem["detail"]


def test_correlation_too_large_even_for_one_target_names_the_measurement(tmp_path: Path) -> None:
    """When even K = 1 is above the limit, the measurement itself is named (and the power
    form suggested)."""
    settings = make_settings(tmp_path, embedded_workers=1, max_localize_work=95)
    with TestClient(create_app(settings)) as client:
        room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
        wait_for_room(client, room["id"])
        body = {"correlation": [1e-12, 0.0, 2e-12], "targets": 1}
        response = client.post(f"/v1/rooms/{room['id']}/localize", json=body, headers=TERMINAL)
        problem = assert_problem(response, 422, ["body.correlation"])
        assert "power" in problem["detail"]


def test_default_localize_work_admits_the_hall_as_power_or_terminals_not_as_correlation() -> None:
    """The million-point hall (bench/hall_build.py: 10^6 points, 1024 LEDs): up to 64
    targets as power or terminals fit the default; its correlation matrix (524800
    observations) does not, even for one target."""
    limit = Settings().max_localize_work
    hall = {"n_cells": 1_000_000, "n_leds": 1024}
    assert localize_work(**hall, model="power", targets=64).units == 64 * 1024 * 10**6 <= limit
    assert localize_work(**hall, model="correlation", targets=None, terminals=64).units <= limit
    one = localize_work(**hall, model="correlation", targets=1)
    assert one.observations == 1024 * 1025 // 2 and one.units > limit
