"""Localize: every input form, every solver, terminal labels, validation, caching."""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any, get_args

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.clock import FakeClock
from app.main import create_app
from app.schemas import SolverName
from app.vlp.errors import SolverFailed
from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import measurement_from_correlation, vech
from app.vlp.solvers import l1 as l1_module
from app.vlp.solvers import make_solver, solver_names

from .conftest import (
    ADMIN,
    TERMINAL,
    TestClient,
    assert_problem,
    make_settings,
    small_room,
    wait_for_room,
)

# Two grid cells of the paper room (0.2 m grid, n_y = 20): centres (1.3, 0.5) and (2.7, 3.1).
CELLS = [6 * 20 + 2, 13 * 20 + 15]


def matched_error(estimates: list[dict[str, Any]], truth: list[dict[str, Any]]) -> float:
    """Largest distance under the best one-to-one matching (brute force; K is small)."""
    assert len(estimates) == len(truth)
    return min(
        max(math.hypot(e["x"] - t["x"], e["y"] - t["y"]) for e, t in zip(order, truth, strict=True))
        for order in itertools.permutations(estimates)
    )


def on_grid_amplitudes(fingerprint: Fingerprint) -> np.ndarray[Any, Any]:
    """Noiseless amplitudes h_ij x_i of terminals at CELLS, straight from H, shape (K, M)."""
    gains = fingerprint.gains.toarray()[:, CELLS]
    return np.asarray((gains * fingerprint.pilot_amplitudes[:, None]).T)


def localize(client: TestClient, room_id: str, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    result: dict[str, Any] = response.json()
    return result


@pytest.mark.parametrize("solver", ["gridless", "nnls", "omp", "l1"])
def test_answer_equals_the_solver_called_directly(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint, solver: str
) -> None:
    client, room_id = ready_app
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    correlation = amplitudes.T @ amplitudes
    result = localize(
        client, room_id, {"correlation": correlation.tolist(), "targets": 2, "solver": solver}
    )
    assert result["solver"] == solver and result["model"] == "correlation"
    assert result["targets"] == 2 and result["fingerprint_version"] >= 1
    direct = make_solver(solver, paper_fingerprint, "correlation").solve(
        measurement_from_correlation(correlation, 16), 2
    )
    assert_allclose(
        [[e["x"], e["y"]] for e in result["estimates"]], direct.positions, rtol=0, atol=1e-9
    )
    assert [e["grid_index"] for e in result["estimates"]] == direct.grid_indices.tolist()
    assert_allclose([e["weight"] for e in result["estimates"]], direct.weights, rtol=1e-9)
    assert all(e["terminal_id"] is None for e in result["estimates"])
    assert result["elapsed_ms"] >= 0
    assert result["residual_norm"] == pytest.approx(direct.residual_norm, rel=1e-6, abs=1e-18)
    assert result["converged"] is bool(direct.converged)


@pytest.mark.parametrize("solver", ["gridless", "omp"])
def test_answer_is_json_with_exactly_the_localization_members(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint, solver: str
) -> None:
    """The answer carries every member of a `Localization` and of each `Estimate` (nulls
    included, as the document says) and no tracking members when `track` is not asked."""
    client, room_id = ready_app
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    body = {"correlation": (amplitudes.T @ amplitudes).tolist(), "targets": 2, "solver": solver}
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/json"
    answer = response.json()
    assert set(answer) == {
        "room_id",
        "fingerprint_version",
        "model",
        "solver",
        "targets",
        "estimates",
        "residual_norm",
        "noise_power",
        "elapsed_ms",
        "converged",
        "fit",
    }
    estimate_members = {"x", "y", "grid_index", "weight", "terminal_id"}
    estimate_members |= {"accuracy_m", "covariance", "gain", "z"}
    assert [set(e) for e in answer["estimates"]] == [estimate_members] * 2
    if solver == "omp":  # no fit, no uncertainty: nulls, not left out
        assert answer["fit"] is None
        assert all(e["accuracy_m"] is None and e["covariance"] is None for e in answer["estimates"])
    else:
        assert set(answer["fit"]) == {"quality", "chi2_per_dof", "scale", "detail"}
        assert all(len(e["covariance"]) == 2 for e in answer["estimates"])


def test_the_contract_offers_exactly_the_registered_solvers() -> None:
    assert sorted(get_args(SolverName)) == sorted(solver_names())


def test_a_solver_that_finds_no_answer_is_a_503_not_invalid_input(
    ready_app: tuple[TestClient, str],
    paper_fingerprint: Fingerprint,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The client's input was fine: the answer names the solver's failure, no field."""
    client, room_id = ready_app

    def no_convergence(*_args: object, **_kwargs: object) -> None:
        raise SolverFailed("l1 minimisation did not converge (status 'infeasible')")

    monkeypatch.setattr(l1_module, "_run", no_convergence)
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    body = {"power": (amplitudes**2).sum(axis=0).tolist(), "targets": 2, "solver": "l1"}
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    problem = assert_problem(response, 503)
    assert problem["type"] == "urn:vlp:problem:solver-failed"
    assert "did not converge" in problem["detail"] and "errors" not in problem


@pytest.mark.parametrize("solver", ["gridless", "nnls", "l1"])
def test_noiseless_on_grid_targets_are_found_exactly(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint, solver: str
) -> None:
    client, room_id = ready_app
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    correlation = amplitudes.T @ amplitudes
    result = localize(
        client, room_id, {"correlation": correlation.tolist(), "targets": 2, "solver": solver}
    )
    assert sorted(e["grid_index"] for e in result["estimates"]) == sorted(CELLS)
    truth = [
        {"x": x, "y": y} for x, y in paper_fingerprint.layout.cell_centres(np.array(CELLS)).tolist()
    ]
    assert matched_error(result["estimates"], truth) < 0.02


@pytest.mark.parametrize(
    "model, form",
    [
        ("power", "matrix"),
        ("correlation", "matrix"),
        ("correlation", "upper"),
        ("correlation", "terminals"),
        ("power", "terminals"),
    ],
)
def test_simulate_then_localize_every_form(
    ready_app: tuple[TestClient, str], model: str, form: str
) -> None:
    client, room_id = ready_app
    simulation = client.post(
        f"/v1/rooms/{room_id}/simulate",
        headers=TERMINAL,
        json={"targets": 2, "snr_db": 30, "model": model, "form": form, "seed": 11},
    )
    assert simulation.status_code == 200, simulation.text
    sim = simulation.json()
    body = sim["measurement"]
    expected_key = (
        "terminals" if form == "terminals" else ("power" if model == "power" else "correlation")
    )
    assert expected_key in body and body["model"] == model and body["targets"] == 2
    result = localize(client, room_id, body)
    assert result["model"] == model
    assert matched_error(result["estimates"], sim["truth"]) < 0.3
    if form == "terminals":
        # Every estimate is labelled with the terminal whose truth it is closest to.
        for estimate in result["estimates"]:
            nearest = min(
                sim["truth"],
                key=lambda t: math.hypot(t["x"] - estimate["x"], t["y"] - estimate["y"]),
            )
            assert estimate["terminal_id"] == nearest["terminal_id"]


def test_correlation_matrix_and_upper_triangle_agree(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint
) -> None:
    client, room_id = ready_app
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    correlation = amplitudes.T @ amplitudes
    full = localize(client, room_id, {"correlation": correlation.tolist(), "solver": "nnls"})
    upper = localize(client, room_id, {"correlation": vech(correlation).tolist(), "solver": "nnls"})
    terminals = localize(
        client,
        room_id,
        {
            "solver": "nnls",
            "terminals": [
                {"id": "a", "amplitudes": amplitudes[0].tolist()},
                {"id": "b", "amplitudes": amplitudes[1].tolist()},
            ],
        },
    )
    assert full["estimates"] == upper["estimates"]
    assert [e["grid_index"] for e in terminals["estimates"]] == [
        e["grid_index"] for e in full["estimates"]
    ]
    owner = {e["grid_index"]: e["terminal_id"] for e in terminals["estimates"]}
    assert owner == {CELLS[0]: "a", CELLS[1]: "b"}
    # Without `targets` the service estimates the count.
    assert full["targets"] == 2


def test_power_with_default_model(
    ready_app: tuple[TestClient, str], paper_fingerprint: Fingerprint
) -> None:
    client, room_id = ready_app
    amplitudes = on_grid_amplitudes(paper_fingerprint)
    power = (amplitudes**2).sum(axis=0)
    result = localize(client, room_id, {"power": power.tolist(), "targets": 2, "solver": "nnls"})
    assert result["model"] == "power"
    assert sorted(e["grid_index"] for e in result["estimates"]) == sorted(CELLS)


def _bad(client: TestClient, room_id: str, body: dict[str, Any], fields: list[str]) -> None:
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert_problem(response, 422, fields)


def test_invalid_measurements_name_the_field(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    ones = [1e-10] * 16
    _bad(client, room_id, {}, ["body.power", "body.correlation", "body.terminals"])
    _bad(client, room_id, {"power": ones, "correlation": ones}, ["body.power", "body.correlation"])
    _bad(client, room_id, {"power": ones, "model": "correlation"}, ["body.model"])
    _bad(client, room_id, {"correlation": ones, "model": "power"}, ["body.model"])
    _bad(client, room_id, {"power": [1e-10] * 15}, ["body.power"])
    _bad(client, room_id, {"power": [-1e-10] * 16}, ["body.power"])
    asymmetric = np.eye(16)
    asymmetric[0, 1] = 1.0
    _bad(client, room_id, {"correlation": asymmetric.tolist()}, ["body.correlation"])
    _bad(client, room_id, {"correlation": [1.0] * 17}, ["body.correlation"])
    _bad(
        client,
        room_id,
        {"terminals": [{"id": "a", "amplitudes": ones}, {"id": "b", "amplitudes": [1.0]}]},
        ["body.terminals.1.amplitudes"],
    )
    _bad(
        client,
        room_id,
        {"terminals": [{"id": "a", "amplitudes": ones}, {"id": "a", "amplitudes": ones}]},
        ["body.terminals.1.id"],
    )
    _bad(client, room_id, {"power": ones, "targets": 0}, ["body.targets"])
    _bad(client, room_id, {"power": ones, "targets": 65}, ["body.targets"])
    _bad(client, room_id, {"power": ones, "solver": "magic"}, ["body.solver"])
    _bad(client, room_id, {"power": ones, "fingerprint_version": 0}, ["body.fingerprint_version"])
    response = client.post(
        f"/v1/rooms/{room_id}/localize",
        headers={**TERMINAL, "Content-Type": "application/json"},
        content=b'{"power": [NaN' + b", 1.0" * 15 + b"]}",
    )
    assert_problem(response, 422)


def test_unknown_room_or_version_is_404(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    body = {"power": [1e-10] * 16}
    assert_problem(client.post("/v1/rooms/nope/localize", json=body, headers=TERMINAL), 404)
    assert_problem(
        client.post(
            f"/v1/rooms/{room_id}/localize",
            headers=TERMINAL,
            json={**body, "fingerprint_version": 99},
        ),
        404,
    )


def test_localize_before_ready_is_409(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    problem = assert_problem(
        client.post(
            f"/v1/rooms/{room['id']}/localize", headers=TERMINAL, json={"power": [1.0, 1.0]}
        ),
        409,
    )
    assert "fingerprint" in problem["detail"]


def test_other_process_notices_a_new_version_after_the_check_interval(tmp_path: Path) -> None:
    """Two apps on one registry: B only reads, on a stepped clock; A replaces the room and
    builds version 2. B answers with version 1 until its re-read interval (1 s) has passed
    on its clock, and the next request after that answers with version 2."""
    clock = FakeClock()
    builder = TestClient(create_app(make_settings(tmp_path, demo=True, embedded_workers=1)))
    reader = TestClient(create_app(make_settings(tmp_path, version_check_seconds=1.0), clock=clock))
    with builder, reader:
        room = builder.get("/v1/rooms", headers=ADMIN).json()["items"][0]
        room = wait_for_room(builder, room["id"])
        body = {
            "terminals": [{"id": "t", "amplitudes": [1e-6] * 16}],
            "solver": "nnls",
            "targets": 1,
        }
        first = localize(reader, room["id"], body)["fingerprint_version"]
        layout = room["layout"] | {
            "leds": [dict(led, pilot_amplitude=2.0) for led in room["layout"]["leds"]]
        }
        etag = f'"{room["id"]}-{room["layout_version"]}"'
        put = builder.put(
            f"/v1/rooms/{room['id']}", json=layout, headers={**ADMIN, "If-Match": etag}
        )
        assert put.status_code == 200, put.text
        rebuilt = wait_for_room(builder, room["id"])["fingerprint"]["version"]
        assert rebuilt == first + 1
        assert localize(reader, room["id"], body)["fingerprint_version"] == first
        clock.advance(0.5)
        assert localize(reader, room["id"], body)["fingerprint_version"] == first
        clock.advance(0.5)  # the interval has passed since B last read the version
        assert localize(reader, room["id"], body)["fingerprint_version"] == rebuilt
