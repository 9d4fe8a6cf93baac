"""Simulate: measurements equal an independent computation; validation; reproducibility."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import vech

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, small_room

CELLS = [6 * 20 + 2, 13 * 20 + 15]


def simulate(client: TestClient, room_id: str, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room_id}/simulate", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    result: dict[str, Any] = response.json()
    return result


@pytest.mark.parametrize(
    "model, form",
    [
        ("correlation", "matrix"),
        ("correlation", "upper"),
        ("power", "matrix"),
        ("correlation", "terminals"),
    ],
)
def test_noiseless_measurement_matches_H(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint, model: str, form: str
) -> None:
    client, room_id = ready_app
    centres = paper_fingerprint.layout.cell_centres(np.array(CELLS))
    sim = simulate(
        client,
        room_id,
        {
            "positions": centres.tolist(),
            "noise_std": 0.0,
            "model": model,
            "form": form,
            "solver": "nnls",
        },
    )
    amplitudes = (
        paper_fingerprint.gains.toarray()[:, CELLS] * paper_fingerprint.pilot_amplitudes[:, None]
    ).T
    body = sim["measurement"]
    assert body["model"] == model and body["solver"] == "nnls" and body["targets"] == 2
    assert body["fingerprint_version"] == sim["fingerprint_version"]
    assert sim["noise_std"] == 0.0
    if form == "terminals":
        assert [t["id"] for t in body["terminals"]] == ["t1", "t2"]
        assert_allclose([t["amplitudes"] for t in body["terminals"]], amplitudes, rtol=1e-12)
    elif model == "power":
        assert_allclose(body["power"], (amplitudes**2).sum(axis=0), rtol=1e-12)
    elif form == "matrix":
        assert_allclose(body["correlation"], amplitudes.T @ amplitudes, rtol=1e-12)
    else:
        assert_allclose(body["correlation"], vech(amplitudes.T @ amplitudes), rtol=1e-12)
    assert [t["grid_index"] for t in sim["truth"]] == CELLS
    assert_allclose([[t["x"], t["y"]] for t in sim["truth"]], centres)
    ids = [t["terminal_id"] for t in sim["truth"]]
    assert ids == (["t1", "t2"] if form == "terminals" else [None, None])


def test_noise_follows_snr_and_seed(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint
) -> None:
    client, room_id = ready_app
    body = {"targets": 3, "snr_db": 20, "seed": 5, "form": "terminals"}
    first, second = simulate(client, room_id, body), simulate(client, room_id, body)
    assert first == second
    other = simulate(client, room_id, {**body, "seed": 6})
    assert other["truth"] != first["truth"]
    # SNR convention: sigma^2 = mean(J) / 10^(snr/10).
    power = paper_fingerprint.gains.toarray() ** 2
    assert first["noise_std"] == pytest.approx(np.sqrt(power.mean() / 100.0), rel=1e-12)
    default = simulate(client, room_id, {"targets": 1, "seed": 1})
    assert default["noise_std"] == pytest.approx(np.sqrt(power.mean() / 1000.0), rel=1e-12)
    # Random terminals lie in distinct cells inside the room.
    cells = [t["grid_index"] for t in first["truth"]]
    assert len(set(cells)) == 3
    assert all(0 <= t["x"] <= 4 and 0 <= t["y"] <= 4 for t in first["truth"])


def test_invalid_simulations_name_the_field(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app

    def bad(body: dict[str, Any], fields: list[str]) -> None:
        response = client.post(f"/v1/rooms/{room_id}/simulate", json=body, headers=TERMINAL)
        assert_problem(response, 422, fields)

    bad({}, ["body.targets", "body.positions"])
    bad({"targets": 1, "positions": [[1, 1]]}, ["body.targets", "body.positions"])
    bad({"targets": 1, "snr_db": 10, "noise_std": 0.1}, ["body.snr_db", "body.noise_std"])
    bad({"positions": [[1, 1], [4.5, 1]]}, ["body.positions.1"])
    bad({"targets": 0}, ["body.targets"])
    bad({"targets": 1, "form": "csv"}, ["body.form"])
    bad({"targets": 1, "noise_std": -1}, ["body.noise_std"])


def test_simulate_before_ready_is_409_and_unknown_room_404(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    assert_problem(
        client.post(f"/v1/rooms/{room['id']}/simulate", json={"targets": 1}, headers=TERMINAL), 409
    )
    assert_problem(
        client.post("/v1/rooms/nope/simulate", json={"targets": 1}, headers=TERMINAL), 404
    )
