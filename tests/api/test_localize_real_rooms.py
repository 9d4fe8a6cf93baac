"""Localize answers for real rooms: per-terminal fits, uncertainty, fit quality, scale checks."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from app.vlp.presets import paper_layout
from app.vlp.simulation import (
    Impairments,
    random_positions,
    simulate_terminals,
    true_amplitudes,
)

from .conftest import TERMINAL, TestClient, assert_problem

TRUTH = np.array([[0.8, 1.1], [2.9, 3.2], [2.2, 0.6]])


def _localize(client: TestClient, room_id: str, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    answer: dict[str, Any] = response.json()
    return answer


def _terminals(amplitudes: np.ndarray, **extra: Any) -> list[dict[str, Any]]:
    return [
        {"id": f"phone-{k}", "amplitudes": row.tolist(), **extra}
        for k, row in enumerate(amplitudes)
    ]


def test_terminals_are_each_located_and_labelled_in_order(
    ready_app: tuple[TestClient, str],
) -> None:
    client, room_id = ready_app
    gains = np.array([1.0, 0.85, 1.15])
    amplitudes = true_amplitudes(paper_layout(), TRUTH) * gains[:, None]
    # 40 dB of noise: the fit's chi-square compares the residuals with it.
    noise = (
        1e-2
        * np.sqrt(np.mean(amplitudes**2))
        * np.random.default_rng(3).standard_normal(amplitudes.shape)
    )
    answer = _localize(client, room_id, {"terminals": _terminals(amplitudes + noise)})
    assert answer["targets"] == 3  # left out: one per terminal sent
    estimates = answer["estimates"]
    assert [e["terminal_id"] for e in estimates] == ["phone-0", "phone-1", "phone-2"]
    positions = np.array([[e["x"], e["y"]] for e in estimates])
    np.testing.assert_allclose(positions, TRUTH, atol=0.02)
    np.testing.assert_allclose([e["gain"] for e in estimates], gains, rtol=0.05)
    for estimate in estimates:
        covariance = np.array(estimate["covariance"])
        assert covariance.shape == (2, 2)
        np.testing.assert_allclose(covariance, covariance.T)
        assert estimate["accuracy_m"] >= 2.0 * math.sqrt(max(np.linalg.eigvalsh(covariance)))
    assert answer["fit"]["quality"] == "ok"


def test_a_sent_height_and_normal_are_used(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    body = {
        "terminals": [
            {
                "id": "tilted",
                "amplitudes": true_amplitudes(paper_layout(), TRUTH[:1])[0].tolist(),
                "height": 0.85,
                "normal": [0.0, 0.0, 2.0],  # not unit: normalised by the service
            }
        ]
    }
    answer = _localize(client, room_id, body)
    estimate = answer["estimates"][0]
    assert estimate["z"] == pytest.approx(0.85)
    assert [estimate["x"], estimate["y"]] == pytest.approx(TRUTH[0].tolist(), abs=2e-3)


@pytest.mark.parametrize("normal", [[0.0, 0.0, 0.0], [1.0, 0.0, -0.1], [1.0, 0.0, 0.0]])
def test_a_normal_that_does_not_point_up_is_refused(
    ready_app: tuple[TestClient, str], normal: list[float]
) -> None:
    client, room_id = ready_app
    amplitudes = true_amplitudes(paper_layout(), TRUTH)
    terminals = _terminals(amplitudes)
    terminals[1]["normal"] = normal
    response = client.post(
        f"/v1/rooms/{room_id}/localize", json={"terminals": terminals}, headers=TERMINAL
    )
    assert_problem(response, 422, ["body.terminals.1.normal"])


def test_a_correlation_a_thousand_times_too_large_is_refused_naming_the_factor(
    ready_app: tuple[TestClient, str],
) -> None:
    client, room_id = ready_app
    amplitudes = true_amplitudes(paper_layout(), TRUTH)
    correlation = 1000.0 * amplitudes.T @ amplitudes
    body = {"correlation": correlation.tolist(), "targets": 3}
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    problem = assert_problem(response, 422, ["body.correlation"])
    assert "x larger" in problem["detail"] and "units" in problem["detail"]
    flagged = _localize(client, room_id, {**body, "correlation": (correlation / 100).tolist()})
    assert flagged["fit"]["quality"] == "scale_mismatch"
    assert flagged["fit"]["scale"] == pytest.approx(math.sqrt(10.0), rel=0.05)


def test_grid_solvers_answer_without_a_fit_block(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    amplitudes = true_amplitudes(paper_layout(), TRUTH)
    answer = _localize(client, room_id, {"terminals": _terminals(amplitudes), "solver": "nnls"})
    assert answer["fit"] is None
    assert all(e["accuracy_m"] is None for e in answer["estimates"])
    assert sorted(e["terminal_id"] for e in answer["estimates"]) == [
        "phone-0",
        "phone-1",
        "phone-2",
    ]


def test_leds_off_their_data_sheet_are_fitted_and_said(ready_app: tuple[TestClient, str]) -> None:
    # LEDs 5 % / 3 degrees off the layout (the paper room as seeded): the default solver
    # fits their tolerances when the data show them, and the answer's fit says so.
    client, room_id = ready_app
    layout = paper_layout()
    details = []
    for seed in range(4):
        truth = random_positions(layout, 8, rng=np.random.default_rng(1000 + seed))
        simulated = simulate_terminals(
            layout, truth, Impairments.led_tolerances(0.05, 3.0), snr_db=30.0, rng=seed
        )
        correlation = simulated.amplitudes.T @ simulated.amplitudes
        answer = _localize(client, room_id, {"correlation": correlation.tolist(), "targets": 8})
        positions = np.array([[e["x"], e["y"]] for e in answer["estimates"]])
        nearest = np.linalg.norm(truth[:, None, :] - positions[None, :, :], axis=2).min(axis=1)
        assert np.median(nearest) < 0.25
        assert all(math.isfinite(e["accuracy_m"]) for e in answer["estimates"])
        details.append(answer["fit"]["detail"])
    assert any("tolerances were fitted" in detail for detail in details)
