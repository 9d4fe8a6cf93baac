"""The same app's lifespan run twice (one after the other, and one inside the other)."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.main import create_app

from .conftest import ADMIN, TestClient, make_settings, small_room, wait_for_room


@pytest.mark.slow
def test_lifespan_twice_keeps_building_and_fails_no_job(tmp_path: Path) -> None:
    app = create_app(make_settings(tmp_path, embedded_workers=1))
    room_ids = []
    for _ in range(2):
        with TestClient(app) as client:
            room_ids.append(client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"])
            wait_for_room(client, room_ids[-1])
    with TestClient(app) as outer:
        with TestClient(app) as inner:
            room_ids.append(inner.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"])
            wait_for_room(inner, room_ids[-1])
        # The inner lifespan stopped its workers; the outer one's still build.
        room_ids.append(outer.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"])
        wait_for_room(outer, room_ids[-1])
    with TestClient(app) as client:
        for room_id in room_ids:
            room = client.get(f"/v1/rooms/{room_id}", headers=ADMIN).json()
            job = client.get(f"/v1/jobs/{room['fingerprint']['job_id']}", headers=ADMIN).json()
            assert (room["fingerprint"]["status"], job["status"], job["attempts"]) == (
                "ready",
                "succeeded",
                1,
            )
