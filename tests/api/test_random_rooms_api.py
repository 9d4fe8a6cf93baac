"""Requests from bench/random_rooms.py that once answered 500, or confidently wrong, through
the API."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from app.vlp.layout import Layout
from app.vlp.metrics import match_positions
from bench.random_rooms import WRONG_M, replay_request

from .conftest import ADMIN, TERMINAL, TestClient, wait_for_room

pytestmark = pytest.mark.slow


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
    layout, body, _truth = replay_request(seed, room, trial)
    estimates = _answer(worker_app, layout, body)["estimates"]
    diagonal = math.hypot(layout.room.length, layout.room.width)
    for estimate in estimates:
        assert 0.0 < estimate["accuracy_m"] <= diagonal * (1 + 1e-9)
        assert 0.0 <= estimate["x"] <= layout.room.length
        assert 0.0 <= estimate["y"] <= layout.room.width


@pytest.mark.parametrize(
    ("seed", "room", "trial"),
    [
        (1, 8, 3),  # correlation, K = 3 given, ideal, 20 dB: one estimate 6.2 m off, radius 2.5
        (1, 1, 4),  # correlation, K = 1, realistic mix, 8 LEDs: 4.4 m off, radius 1.9
        (1, 24, 6),  # correlation, K = 2, mix, 10 dB: 4.5 m off, radius 2.1
        (1, 15, 7),  # power, K = 2 given, mix: 1.1 m off, radius 0.45
        (1, 32, 6),  # power, K unknown, mix, 10 dB: 3.8 m off, radius 1.3
        # Estimates stuck at a far optimum that fits to the noise, now tried there and moved
        # (GridlessOptions.relocate_ambiguous):
        (4, 38, 1),  # correlation, K = 2 given, ideal, 30 dB, 8 LEDs: 1.9 m off, radius 1.7
        (4, 20, 2),  # correlation, K unknown, ideal, 30 dB, 9 LEDs: 6.2 m off, radius 2.6
        (4, 19, 4),  # correlation, K = 5 given, ideal, 40 dB, 9 LEDs: 3.7 m off, radius 3.6
    ],
)
def test_once_confidently_wrong_now_a_radius_that_holds_the_truth(
    worker_app: TestClient, seed: int, room: int, trial: int
) -> None:
    """Aggregated answers whose estimate sat at one of two places that fit about as well,
    with a radius that knew only its own (quality ok): each estimate is now moved over the
    grid with the others held, and its radius holds the farthest place that fits as well."""
    layout, body, truth = replay_request(seed, room, trial)
    answer = _answer(worker_app, layout, body)
    assert answer["fit"]["quality"] == "ok"
    estimates = np.array([[e["x"], e["y"]] for e in answer["estimates"]])
    radii = np.array([e["accuracy_m"] for e in answer["estimates"]])
    rows, cols = match_positions(estimates, truth)
    distances = np.linalg.norm(estimates[rows] - truth[cols], axis=1)
    assert np.all((distances <= radii[rows]) | (distances <= WRONG_M))
    # Not asserted: that the detail names another place. Which of the places a fit lands at,
    # and whether the far place or the noise alone makes the radius wide, is round-off's
    # choice (one machine: the K = 1 case 0.83 m off with a 6.9 m radius and no far place;
    # another: the K = 2 case 1.17 m off with a 7.8 m radius, no far place beyond it). The
    # detail itself is tested where the case is deterministic (tests/vlp/test_ambiguity.py).


def _answer(client: TestClient, layout: Layout, body: dict[str, Any]) -> dict[str, Any]:
    created = client.post("/v1/rooms", json=layout.to_mapping(), headers=ADMIN)
    assert created.status_code == 201, created.text
    room_id = created.json()["id"]
    wait_for_room(client, room_id)
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    answer: dict[str, Any] = response.json()
    return answer
