"""Localize in batches: order, mixed good and bad items, the item limit, roles, one lookup."""

from __future__ import annotations

from typing import Any

import pytest

from app.schemas import MAX_BATCH_ITEMS, LocalizationBatch

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, small_room


def simulated(client: TestClient, room_id: str, **request: Any) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room_id}/simulate", json=request, headers=TERMINAL)
    assert response.status_code == 200, response.text
    measurement: dict[str, Any] = response.json()["measurement"]
    return measurement


def single(client: TestClient, room_id: str, body: dict[str, Any]) -> dict[str, Any]:
    """What a single localize answers for ``body`` (a localization or a problem)."""
    response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    answer: dict[str, Any] = response.json()
    assert ("status" in answer) == (response.status_code != 200), response.text
    return answer


def batch(
    client: TestClient, room_id: str, items: list[Any], headers: dict[str, str] = TERMINAL
) -> list[dict[str, Any]]:
    response = client.post(
        f"/v1/rooms/{room_id}/localize/batch", json={"items": items}, headers=headers
    )
    assert response.status_code == 200, response.text
    LocalizationBatch.model_validate(response.json())
    answers: list[dict[str, Any]] = response.json()["items"]
    assert len(answers) == len(items)
    return answers


def without_timing(answer: dict[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in answer.items() if key not in ("elapsed_ms", "request_id")}


def test_answers_in_order_equal_to_single_calls(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    items = [
        simulated(client, room_id, targets=1 + seed % 3, snr_db=30, seed=seed) for seed in range(5)
    ]
    items.append({**simulated(client, room_id, targets=2, seed=7), "solver": "omp"})
    answers = batch(client, room_id, items)
    assert [a["targets"] for a in answers] == [1, 2, 3, 1, 2, 2]
    for item, answer in zip(items, answers, strict=True):
        assert without_timing(answer) == without_timing(single(client, room_id, item))


def test_a_bad_item_is_its_problem_in_place(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    good = simulated(client, room_id, targets=2, seed=11)
    items: list[Any] = [
        good,
        {**good, "correlation": "not a matrix"},  # schema: 422
        {"targets": 2},  # none of power, correlation, terminals: 422
        {"power": [1e-9] * 3, "targets": 1},  # 3 powers for 16 LEDs: 422
        {**good, "fingerprint_version": 999},  # no such version: 404
        "not an object",
        {**good, "solver": "omp"},
    ]
    answers = batch(client, room_id, items)
    statuses = [answer.get("status", 200) for answer in answers]
    assert statuses == [200, 422, 422, 422, 404, 422, 200]
    assert without_timing(answers[0]) == without_timing(single(client, room_id, good))
    assert answers[6]["solver"] == "omp"
    assert all(f["field"].startswith("body.items.1.correlation") for f in answers[1]["errors"])
    assert {f["field"] for f in answers[2]["errors"]} == {
        "body.items.2.power",
        "body.items.2.correlation",
        "body.items.2.terminals",
    }
    assert [f["field"] for f in answers[3]["errors"]] == ["body.items.3.power"]
    assert [f["field"] for f in answers[5]["errors"]] == ["body.items.5"]
    for index in (1, 2, 3, 4):  # the problem a single call answers, fields renamed
        alone = single(client, room_id, items[index])
        assert alone["status"] == answers[index]["status"]
        assert alone["type"] == answers[index]["type"]
        renamed = {
            f["field"].replace("body.", f"body.items.{index}.", 1) for f in alone.get("errors", [])
        }
        assert renamed == {f["field"] for f in answers[index].get("errors", [])}
    assert all(a["instance"] == f"/v1/rooms/{room_id}/localize/batch" for a in answers[1:6])


@pytest.mark.parametrize("count", [0, MAX_BATCH_ITEMS + 1])
def test_item_count_is_limited(ready_app: tuple[TestClient, str], count: int) -> None:
    client, room_id = ready_app
    body = {"power": [1e-9] * 16, "targets": 1, "solver": "omp"}
    response = client.post(
        f"/v1/rooms/{room_id}/localize/batch", json={"items": [body] * count}, headers=TERMINAL
    )
    assert_problem(response, 422, ["body.items"])


def test_the_largest_batch_is_answered(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    body = {**simulated(client, room_id, targets=1, seed=5), "solver": "omp"}
    answers = batch(client, room_id, [body] * MAX_BATCH_ITEMS)
    assert {answer.get("status", 200) for answer in answers} == {200}
    assert len({(a["estimates"][0]["x"], a["estimates"][0]["y"]) for a in answers}) == 1


def test_roles(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    path = f"/v1/rooms/{room_id}/localize/batch"
    body = {"items": [{**simulated(client, room_id, targets=1, seed=2), "solver": "omp"}]}
    assert_problem(client.post(path, json=body), 401)
    assert_problem(client.post(path, json=body, headers={"X-API-Key": "x" * 30}), 401)
    assert batch(client, room_id, body["items"], headers=TERMINAL)[0]["targets"] == 1
    assert batch(client, room_id, body["items"], headers=ADMIN)[0]["targets"] == 1


def test_the_room_is_looked_up_once_per_batch(
    ready_app: tuple[TestClient, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The test app re-reads a room's current version on every request
    (``version_check_seconds=0``): a batch reads it once, for all of its items."""
    client, room_id = ready_app
    registry = client.app.state.registry  # type: ignore[attr-defined]
    reads: list[str] = []
    original = registry.current_version

    def counted(*, room_id: str) -> int | None:
        reads.append(room_id)
        version: int | None = original(room_id=room_id)
        return version

    # No `fingerprint_version`: each item asks for the current one.
    body = {**simulated(client, room_id, targets=1, seed=4), "solver": "omp"}
    body.pop("fingerprint_version")
    monkeypatch.setattr(registry, "current_version", counted)
    batch(client, room_id, [body] * 20)
    assert reads == [room_id]
    single(client, room_id, body)
    assert reads == [room_id, room_id]


def test_room_problems_answer_for_the_whole_batch(client: TestClient) -> None:
    body = {"items": [{"power": [1e-9, 1e-9], "targets": 1}]}
    missing = client.post("/v1/rooms/" + "0" * 32 + "/localize/batch", json=body, headers=ADMIN)
    assert_problem(missing, 404)
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    pending = client.post(f"/v1/rooms/{room['id']}/localize/batch", json=body, headers=ADMIN)
    assert_problem(pending, 409)
