"""Real rooms through the API: reflective layouts, height spread, simulated impairments."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout_mapping import layout_from_mapping
from tests.bench_rooms import small_room_layout

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, wait_for_room

PAPER_ROOM = json.loads(Path("examples/paper-room.json").read_text(encoding="utf-8"))
# The benchmarks' small room (4 LEDs, N = 144): a reflection table over a spread of heights
# costs a fraction of the paper room's, and the assertions need no bigger room.
SMALL_ROOM = small_room_layout().to_mapping()
REFLECTIVE = SMALL_ROOM | {
    "name": "Reflective meeting room",
    "room": SMALL_ROOM["room"] | {"reflectance": {"walls": 0.7, "floor": 0.2, "ceiling": 0.8}},
    "grid": SMALL_ROOM["grid"] | {"receiver_height_sd": 0.05},
}


@pytest.fixture(scope="module")
def reflective(worker_app: TestClient) -> tuple[TestClient, dict[str, Any]]:
    response = worker_app.post("/v1/rooms", json=REFLECTIVE, headers=ADMIN)
    assert response.status_code == 201, response.text
    return worker_app, wait_for_room(worker_app, response.json()["id"])


@pytest.mark.slow
def test_a_reflective_layout_is_kept_and_its_h_includes_the_reflections(
    reflective: tuple[TestClient, dict[str, Any]],
) -> None:
    client, room = reflective
    assert room["layout"]["room"]["reflectance"] == {"walls": 0.7, "floor": 0.2, "ceiling": 0.8}
    assert room["layout"]["grid"]["receiver_height_sd"] == 0.05
    response = client.get(f"/v1/rooms/{room['id']}/fingerprints/current/H.npy", headers=TERMINAL)
    assert response.status_code == 200
    served = np.load(io.BytesIO(response.content))
    line_of_sight = build_fingerprint(layout_from_mapping(SMALL_ROOM)).dense_gains()
    expected = build_fingerprint(layout_from_mapping(REFLECTIVE)).dense_gains()
    np.testing.assert_allclose(served, expected, rtol=1e-12)
    extra = served.sum() / line_of_sight.sum() - 1.0
    assert 0.25 < extra < 0.45  # about a third of the light bounces off the walls (of 2.4 m)


@pytest.mark.slow
def test_impaired_simulations_localize_with_their_heights_and_quality(
    reflective: tuple[TestClient, dict[str, Any]],
) -> None:
    client, room = reflective
    impairments = {
        "reflectance": {"walls": 0.7, "floor": 0.2, "ceiling": 0.8},
        "gain_sd": 0.05,
        "height_sd_m": 0.05,
        "tilt_max_deg": 5.0,
    }
    body = {"targets": 4, "snr_db": 30, "seed": 3, "form": "terminals", "impairments": impairments}
    response = client.post(f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    simulation = response.json()
    truth = simulation["truth"]
    assert all(t["z"] is not None and t["gain"] is not None for t in truth)
    assert all(abs(np.linalg.norm(t["normal"]) - 1.0) < 1e-9 for t in truth)
    located = client.post(
        f"/v1/rooms/{room['id']}/localize", json=simulation["measurement"], headers=TERMINAL
    )
    assert located.status_code == 200, located.text
    answer = located.json()
    by_id = {e["terminal_id"]: e for e in answer["estimates"]}
    errors = [
        np.hypot(by_id[t["terminal_id"]]["x"] - t["x"], by_id[t["terminal_id"]]["y"] - t["y"])
        for t in truth
    ]
    assert float(np.mean(errors)) < 0.15
    assert all(by_id[t["terminal_id"]]["z"] is not None for t in truth)
    assert answer["fit"]["quality"] in ("ok", "poor")


@pytest.mark.parametrize(
    "change, fields",
    [
        (
            {
                "room": REFLECTIVE["room"]
                | {"reflectance": {"walls": 1.0, "floor": 0.2, "ceiling": 0.8}}
            },
            ["body.room.reflectance.walls"],
        ),
        (
            {"room": REFLECTIVE["room"] | {"reflectance": {"walls": 0.7}}},
            ["body.room.reflectance.ceiling", "body.room.reflectance.floor"],
        ),
        (
            {"grid": REFLECTIVE["grid"] | {"receiver_height_sd": -0.1}},
            ["body.grid.receiver_height_sd"],
        ),
        (
            {"grid": REFLECTIVE["grid"] | {"receiver_tilt_sd": 45.0}},
            ["body.grid.receiver_tilt_sd"],
        ),
        (
            {"grid": REFLECTIVE["grid"] | {"receiver_tilt_sd": 4.0, "receivers_level": True}},
            ["body.grid.receivers_level"],
        ),
        (
            {"grid": REFLECTIVE["grid"] | {"receivers_level": "sometimes"}},
            ["body.grid.receivers_level"],
        ),
        (
            {"grid": REFLECTIVE["grid"] | {"receivers_level": 0}},
            ["body.grid.receivers_level"],
        ),
    ],
    ids=[
        "reflectance-1",
        "reflectance-incomplete",
        "negative-height-sd",
        "tilt-sd-45",
        "level-and-tilted",
        "level-not-a-boolean",
        "level-zero",
    ],
)
def test_bad_real_room_fields_are_refused_naming_them(
    client: TestClient, change: dict[str, Any], fields: list[str]
) -> None:
    response = client.post("/v1/rooms", json=REFLECTIVE | change, headers=ADMIN)
    assert_problem(response, 422, fields)


def test_impairments_want_the_noise_as_an_snr(client: TestClient) -> None:
    """Refused from the body alone, before the room's fingerprint is needed (an app without
    workers: never built)."""
    room = client.post("/v1/rooms", json=REFLECTIVE, headers=ADMIN).json()
    body = {"targets": 2, "noise_std": 1e-7, "impairments": {"gain_sd": 0.1}}
    response = client.post(f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL)
    assert_problem(response, 422, ["body.noise_std"])


@pytest.mark.slow
def test_a_tilt_spread_in_the_layout_widens_the_radii_not_the_positions(
    worker_app: TestClient,
) -> None:
    """The same measurement in the paper room with and without `grid.receiver_tilt_sd`:
    the same estimates, each radius wider (tests/vlp/test_tilt_spread.py checks the added
    covariance against refits)."""
    answers = []
    for grid in (PAPER_ROOM["grid"], PAPER_ROOM["grid"] | {"receiver_tilt_sd": 5.0}):
        created = worker_app.post("/v1/rooms", json=PAPER_ROOM | {"grid": grid}, headers=ADMIN)
        assert created.status_code == 201, created.text
        room = wait_for_room(worker_app, created.json()["id"])
        assert room["layout"]["grid"]["receiver_tilt_sd"] == grid.get("receiver_tilt_sd", 0.0)
        body = {"targets": 3, "snr_db": 30, "seed": 5, "form": "upper"}
        simulated = worker_app.post(f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL)
        assert simulated.status_code == 200, simulated.text
        located = worker_app.post(
            f"/v1/rooms/{room['id']}/localize",
            json=simulated.json()["measurement"],
            headers=TERMINAL,
        )
        assert located.status_code == 200, located.text
        answers.append(located.json()["estimates"])
    level, tilted = answers
    assert [(e["x"], e["y"]) for e in tilted] == [(e["x"], e["y"]) for e in level]
    # Tilts of 5 degrees per component move an estimate by about 6 cm per axis here: added
    # in quadrature, at least 10 cm of 95 % radius.
    for e, t in zip(level, tilted, strict=True):
        assert t["accuracy_m"] ** 2 - e["accuracy_m"] ** 2 > 0.10**2


def test_terminals_of_a_room_with_level_photodiodes_get_radii_without_tilts(
    worker_app: TestClient,
) -> None:
    """The same eight terminals' amplitudes in the paper room as is and with
    `grid.receivers_level`: the layout keeps the field, and the level room's radii are
    narrower (tests/vlp/test_receivers_level.py measures their coverage over many
    placements)."""
    body = {"targets": 8, "snr_db": 30, "seed": 4, "form": "terminals"}
    radii = []
    measurement = None
    for grid in (PAPER_ROOM["grid"], PAPER_ROOM["grid"] | {"receivers_level": True}):
        created = worker_app.post("/v1/rooms", json=PAPER_ROOM | {"grid": grid}, headers=ADMIN)
        assert created.status_code == 201, created.text
        room = wait_for_room(worker_app, created.json()["id"])
        assert room["layout"]["grid"]["receivers_level"] is grid.get("receivers_level", False)
        if measurement is None:
            simulated = worker_app.post(
                f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL
            )
            assert simulated.status_code == 200, simulated.text
            measurement = simulated.json()["measurement"]
        located = worker_app.post(
            f"/v1/rooms/{room['id']}/localize", json=measurement, headers=TERMINAL
        )
        assert located.status_code == 200, located.text
        radii.append(np.array([e["accuracy_m"] for e in located.json()["estimates"]]))
    plain, level = radii
    assert level.sum() < 0.8 * plain.sum(), (level, plain)


def test_terminals_in_a_room_with_a_tilt_spread_are_fitted_tilted(
    worker_app: TestClient,
) -> None:
    """Terminals with tilted photodiodes, sent as `terminals` without their normals: in a room
    whose layout declares the tilt spread, each terminal's tilt is fitted with it as the
    prior, so the answers move towards the truth (tests/vlp/test_tilt_spread.py measures it
    over many placements); without the spread they are the level fits."""
    body = {
        "targets": 8,
        "snr_db": 30,
        "seed": 2,
        "form": "terminals",
        "impairments": {"tilt_max_deg": 20.0},
    }
    errors = []
    for grid in (PAPER_ROOM["grid"], PAPER_ROOM["grid"] | {"receiver_tilt_sd": 8.2}):
        created = worker_app.post("/v1/rooms", json=PAPER_ROOM | {"grid": grid}, headers=ADMIN)
        assert created.status_code == 201, created.text
        room = wait_for_room(worker_app, created.json()["id"])
        simulated = worker_app.post(f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL)
        assert simulated.status_code == 200, simulated.text
        truth = np.array([[t["x"], t["y"]] for t in simulated.json()["truth"]])
        located = worker_app.post(
            f"/v1/rooms/{room['id']}/localize",
            json=simulated.json()["measurement"],
            headers=TERMINAL,
        )
        assert located.status_code == 200, located.text
        found = np.array([[e["x"], e["y"]] for e in located.json()["estimates"]])
        errors.append(np.linalg.norm(found - truth, axis=1))  # estimate k is terminal k
    level, tilted = errors
    assert not np.array_equal(level, tilted)
    assert tilted.mean() < level.mean()


def test_terminals_under_led_tolerances_say_the_leds_are_off_their_data_sheet(
    worker_app: TestClient,
) -> None:
    """LEDs 5 % / 3 degrees off their data sheet, eight terminals sent as `terminals`: their
    residuals grow with the amplitudes, so the answer is refitted with the brightest LEDs
    weighted down and says so, with the goodness of fit still the layout's own
    (tests/vlp/test_terminal_led_weights.py measures the accuracy)."""
    created = worker_app.post("/v1/rooms", json=PAPER_ROOM, headers=ADMIN)
    assert created.status_code == 201, created.text
    room = wait_for_room(worker_app, created.json()["id"])
    body = {
        "targets": 8,
        "snr_db": 30,
        "seed": 4,
        "form": "terminals",
        "impairments": {"led_amplitude_sd": 0.05, "led_half_power_sd_deg": 3.0},
    }
    simulated = worker_app.post(f"/v1/rooms/{room['id']}/simulate", json=body, headers=TERMINAL)
    assert simulated.status_code == 200, simulated.text
    located = worker_app.post(
        f"/v1/rooms/{room['id']}/localize", json=simulated.json()["measurement"], headers=TERMINAL
    )
    assert located.status_code == 200, located.text
    fit = located.json()["fit"]
    assert fit["quality"] == "ok"
    assert "off their data sheet" in fit["detail"], fit["detail"]
    # Ideal LEDs, the same terminals: nothing of the kind is said.
    ideal = worker_app.post(
        f"/v1/rooms/{room['id']}/simulate", json=body | {"impairments": {}}, headers=TERMINAL
    )
    assert ideal.status_code == 200, ideal.text
    answered = worker_app.post(
        f"/v1/rooms/{room['id']}/localize", json=ideal.json()["measurement"], headers=TERMINAL
    )
    assert answered.status_code == 200, answered.text
    assert "data sheet" not in answered.json()["fit"]["detail"]
