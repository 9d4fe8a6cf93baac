"""Localize on the event loop: once a room's version and solver are in memory, a small
solve is answered without the thread pool, with the answer the pool's path gives."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from starlette.concurrency import run_in_threadpool

import app.api.localize as localize_route
from app.main import create_app
from app.services import localization

from .conftest import ADMIN, TERMINAL, TestClient, make_settings, small_room, wait_for_room


def test_answers_on_the_loop_equal_the_thread_pools(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pooled: list[str] = []

    async def counting(function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        pooled.append(function.__name__)
        return await run_in_threadpool(function, *args, **kwargs)

    monkeypatch.setattr(localize_route, "run_in_threadpool", counting)
    settings = make_settings(tmp_path, embedded_workers=1, version_check_seconds=60.0)
    with TestClient(create_app(settings)) as client:
        room_id = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"]
        wait_for_room(client, room_id)
        simulated = client.post(
            f"/v1/rooms/{room_id}/simulate", json={"targets": 1, "seed": 2}, headers=ADMIN
        ).json()["measurement"]
        path = f"/v1/rooms/{room_id}/localize"
        first = client.post(path, json=simulated, headers=TERMINAL)
        assert first.status_code == 200, first.text
        assert pooled == ["localize_measurement"]  # cold: loaded in the pool
        second = client.post(path, json=simulated, headers=TERMINAL)
        assert second.status_code == 200, second.text
        assert pooled == ["localize_measurement"]  # warm: answered on the loop
        assert second.json()["estimates"] == first.json()["estimates"]
        # a solve above the bound still goes to the pool
        monkeypatch.setattr(
            localize_route,
            "localize_in_memory",
            lambda *args, **kwargs: localization.localize_in_memory(
                *args, **kwargs, max_waitless_work=0
            ),
        )
        third = client.post(path, json=simulated, headers=TERMINAL)
        assert third.json()["estimates"] == first.json()["estimates"]
        assert pooled == ["localize_measurement", "localize_measurement"]
        # a bad body is the same problem on the loop as in the pool
        bad = client.post(path, json={**simulated, "targets": 0}, headers=TERMINAL)
        assert bad.status_code == 422
