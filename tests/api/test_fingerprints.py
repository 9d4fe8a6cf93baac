"""Fingerprints: versions, metadata, downloads checked against a direct build; jobs."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp
from numpy.testing import assert_allclose

from app.main import create_app
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout_mapping import layout_from_mapping
from tests.waiting import wait_for

from .conftest import (
    ADMIN,
    TERMINAL,
    TestClient,
    assert_problem,
    make_settings,
    small_room,
    wait_for_job,
    wait_for_room,
)


def test_metadata_of_current_and_numbered_version_agree(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    current = client.get(f"/v1/rooms/{room_id}/fingerprints/current", headers=TERMINAL)
    assert current.status_code == 200, current.text
    meta = current.json()
    assert meta["room_id"] == room_id and meta["leds"] == 16 and meta["grid_points"] == 400
    assert meta["matrices"]["H"]["shape"] == [16, 400]
    assert meta["matrices"]["psi"]["shape"] == [136, 400]
    numbered = client.get(f"/v1/rooms/{room_id}/fingerprints/{meta['version']}", headers=ADMIN)
    assert numbered.json() == meta
    listing = client.get(f"/v1/rooms/{room_id}/fingerprints", headers=TERMINAL).json()
    assert listing["items"][0] == meta


@pytest.mark.parametrize("name", ["H", "J", "psi"])
def test_downloads_equal_a_direct_build(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint, name: str
) -> None:
    client, room_id = ready_app
    meta = client.get(f"/v1/rooms/{room_id}/fingerprints/current", headers=TERMINAL).json()
    response = client.get(f"/v1/rooms/{room_id}/fingerprints/current/{name}.npy", headers=TERMINAL)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    assert hashlib.sha256(response.content).hexdigest() == meta["matrices"][name]["sha256"]
    assert response.headers["etag"] == f'"{meta["matrices"][name]["sha256"]}"'
    matrix = np.load(io.BytesIO(response.content), allow_pickle=False)
    assert matrix.dtype == np.float64
    gains = paper_fingerprint.gains.toarray()
    scaled = gains * paper_fingerprint.pilot_amplitudes[:, None]
    rows, cols = np.triu_indices(16)
    expected = {"H": gains, "J": scaled**2, "psi": scaled[rows] * scaled[cols]}[name]
    assert_allclose(matrix, expected, rtol=1e-12, atol=0)


def test_download_errors(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    base = f"/v1/rooms/{room_id}/fingerprints"
    assert_problem(client.get(f"{base}/99/H.npy", headers=TERMINAL), 404)
    assert_problem(client.get(f"{base}/99", headers=TERMINAL), 404)
    assert_problem(client.get("/v1/rooms/nope/fingerprints/current/H.npy", headers=TERMINAL), 404)
    # Only H, J, psi exist: anything else (incl. path tricks) is a validation error or 404.
    assert_problem(client.get(f"{base}/current/G.npy", headers=TERMINAL), 422, ["path.matrix"])
    assert client.get(
        f"{base}/current/..%2F..%2Fregistry.sqlite3.npy", headers=TERMINAL
    ).status_code in (404, 422)
    assert_problem(client.get(f"{base}/latest", headers=TERMINAL), 422, ["path.version"])
    # H is dense for this room: the sparse download is refused and points at H.npy.
    problem = assert_problem(client.get(f"{base}/current/H.npz", headers=TERMINAL), 409)
    assert "H.npy" in problem["detail"]


def test_fingerprint_not_ready_is_409(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    base = f"/v1/rooms/{room['id']}/fingerprints"
    assert client.get(base, headers=TERMINAL).json() == {"items": []}
    assert_problem(client.get(f"{base}/current", headers=TERMINAL), 409)
    assert_problem(client.get(f"{base}/current/H.npy", headers=TERMINAL), 409)
    assert_problem(client.get(f"{base}/1", headers=TERMINAL), 404)
    assert_problem(client.get("/v1/rooms/nope/fingerprints", headers=TERMINAL), 404)


def test_rebuild_answers_202_with_job_location(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    response = client.post(f"/v1/rooms/{room['id']}/fingerprints", headers=ADMIN)
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/jobs/{job['id']}"
    # Coalesced with the queued build of the same layout.
    assert job["id"] == room["fingerprint"]["job_id"]
    assert job["status"] == "queued" and job["kind"] == "build_fingerprint"
    assert client.get(response.headers["location"], headers=TERMINAL).json() == job
    assert_problem(client.get("/v1/jobs/nope", headers=TERMINAL), 404)
    assert_problem(client.post("/v1/rooms/nope/fingerprints", headers=ADMIN), 404)


def test_rebuild_job_runs_to_success(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    queued = client.post(f"/v1/rooms/{room_id}/fingerprints", headers=ADMIN).json()
    job = wait_for_job(client, queued["id"])
    assert job["progress"] == 1.0 and job["error"] is None
    version = job["result"]["fingerprint_version"]
    assert version >= 1
    assert (
        client.get(f"/v1/rooms/{room_id}", headers=TERMINAL).json()["fingerprint"]["version"]
        == version
    )


def hall_body() -> dict[str, Any]:
    """A 40 x 100 m hall (N = 16000, 256 LEDs): H is stored sparse, J and psi are not stored."""
    leds = [{"x": 2.5 + 2.5 * (i % 16), "y": 3.0 + 6.0 * (i // 16)} for i in range(256)]
    return {
        "name": "Hall",
        "room": {"length": 40.0, "width": 100.0, "height": 3.0},
        "grid": {"step": 0.5, "receiver_height": 0.85},
        "leds": leds,
    }


def test_sparse_room_serves_H_npz_only(tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(tmp_path, embedded_workers=1))) as client:
        room = client.post("/v1/rooms", json=hall_body(), headers=ADMIN).json()
        wait_for_room(client, room["id"])
        base = f"/v1/rooms/{room['id']}/fingerprints/current"
        meta = client.get(base, headers=TERMINAL).json()
        assert meta["matrices"]["H"]["format"] == "npz"
        assert meta["matrices"]["H"]["shape"] == [256, 16000]
        response = client.get(f"{base}/H.npz", headers=TERMINAL)
        assert response.status_code == 200, response.text
        assert hashlib.sha256(response.content).hexdigest() == meta["matrices"]["H"]["sha256"]
        gains = sp.load_npz(io.BytesIO(response.content))
        expected = build_fingerprint(layout_from_mapping(room["layout"])).gains
        assert gains.shape == (256, 16000)
        assert abs(gains - expected).max() <= 1e-12 * abs(expected).max()
        problem = assert_problem(client.get(f"{base}/H.npy", headers=TERMINAL), 409)
        assert "H.npz" in problem["detail"]
        for name in ("J", "psi"):
            problem = assert_problem(client.get(f"{base}/{name}.npy", headers=TERMINAL), 409)
            assert "not materialised" in problem["detail"]


def test_corrupt_matrix_is_never_served_and_gets_rebuilt(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, demo=True, embedded_workers=1)
    with TestClient(create_app(settings)) as client:
        room_id = client.get("/v1/rooms", headers=ADMIN).json()["items"][0]["id"]
        wait_for_room(client, room_id)
        meta = client.get(f"/v1/rooms/{room_id}/fingerprints/current", headers=ADMIN).json()
        sha = meta["matrices"]["J"]["sha256"]
        (path,) = [p for p in tmp_path.rglob(f"*{sha}*") if p.is_file()]
        path.chmod(0o644)
        path.write_bytes(b"not the matrix")
        url = f"/v1/rooms/{room_id}/fingerprints/{meta['version']}/J.npy"
        problem = assert_problem(client.get(url, headers=TERMINAL), 503)
        assert "not the matrix" not in problem["detail"]
        wait_for(lambda: client.get(url, headers=TERMINAL).status_code == 200, "the rebuild")
        response = client.get(url, headers=TERMINAL)
        assert hashlib.sha256(response.content).hexdigest() == sha
