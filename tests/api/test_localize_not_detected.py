"""Localize with LEDs not detected: null amplitudes and a terminal's detection floor."""

from __future__ import annotations

from typing import Any

import numpy as np

from app.vlp.presets import paper_layout
from app.vlp.simulation import true_amplitudes

from .conftest import TERMINAL, TestClient, assert_problem

TRUTH = np.array([[0.4, 0.5], [3.5, 3.3]])


def _body(amplitudes: np.ndarray, floor: float | None = None) -> dict[str, Any]:
    floor_field = {} if floor is None else {"detection_floor": floor}
    return {
        "terminals": [
            {
                "id": f"tag-{k}",
                "amplitudes": [None if np.isnan(a) else float(a) for a in row],
                **floor_field,
            }
            for k, row in enumerate(amplitudes)
        ]
    }


def test_null_amplitudes_are_censored_and_the_terminals_located(
    ready_app: tuple[TestClient, str],
) -> None:
    client, room_id = ready_app
    clean = true_amplitudes(paper_layout(), TRUTH)
    floor = 0.25 * float(clean.max())
    sent = np.where(clean < floor, np.nan, clean)
    assert np.isnan(sent).sum(axis=1).min() >= 6  # most LEDs are not detected
    for body in (_body(sent, floor), _body(sent)):  # own floor, then the default one
        response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
        assert response.status_code == 200, response.text
        estimates = response.json()["estimates"]
        assert [e["terminal_id"] for e in estimates] == ["tag-0", "tag-1"]
        found = np.array([[e["x"], e["y"]] for e in estimates])
        assert np.linalg.norm(found - TRUTH, axis=1).max() < 0.05


def test_a_terminal_that_detected_nothing_or_a_bad_floor_is_a_422_naming_the_field(
    ready_app: tuple[TestClient, str],
) -> None:
    client, room_id = ready_app
    amplitudes = true_amplitudes(paper_layout(), TRUTH)
    nothing = _body(amplitudes)
    nothing["terminals"][1]["amplitudes"] = [None] * amplitudes.shape[1]
    response = client.post(f"/v1/rooms/{room_id}/localize", json=nothing, headers=TERMINAL)
    assert_problem(response, 422, ["body.terminals.1.amplitudes"])
    response = client.post(
        f"/v1/rooms/{room_id}/localize", json=_body(amplitudes, floor=-1.0), headers=TERMINAL
    )
    problem = assert_problem(response, 422)
    assert any("detection_floor" in error["field"] for error in problem["errors"])
