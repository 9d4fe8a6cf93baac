"""Requests from bench/random_rooms.py that once answered 500, through the API."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.random_rooms import draw_request, random_layout

from .conftest import ADMIN, TERMINAL, TestClient, wait_for_room


@pytest.mark.parametrize(
    ("seed", "room", "trial"),
    [
        (2, 0, 1),  # power, K = 1 given, 4 LEDs: 0/0 in the misfit's non-negative fit
        (2, 6, 10),  # the same, another room
        (3, 33, 3),  # correlation, K unknown, 3 LEDs, realistic mix
    ],
)
def test_once_a_500_now_an_answer_with_honest_radii(
    worker_app: TestClient, seed: int, room: int, trial: int
) -> None:
    rng = np.random.default_rng([seed, room])
    layout = random_layout(rng)
    for _ in range(trial + 1):
        body, _truth, _outcome = draw_request(rng, layout, room)
    created = worker_app.post("/v1/rooms", json=layout.to_mapping(), headers=ADMIN)
    assert created.status_code == 201, created.text
    room_id = created.json()["id"]
    wait_for_room(worker_app, room_id)
    response = worker_app.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    estimates = response.json()["estimates"]
    diagonal = math.hypot(layout.room.length, layout.room.width)
    for estimate in estimates:
        assert 0.0 < estimate["accuracy_m"] <= diagonal * (1 + 1e-9)
        assert 0.0 <= estimate["x"] <= layout.room.length
        assert 0.0 <= estimate["y"] <= layout.room.width
