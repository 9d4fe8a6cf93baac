"""Small items of the HTTP contract: `GET /`, 415 without a JSON Content-Type, malformed JSON names
the body, `If-None-Match` on a room, `Retry-After` on 202 answers."""

from __future__ import annotations

from pathlib import Path

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, small_room
from .test_epochs import create, post, room_of, start


def test_root_redirects_to_the_docs(client: TestClient) -> None:
    answer = client.get("/", follow_redirects=False)
    assert answer.status_code == 307 and answer.headers["location"] == "/docs"
    assert client.get("/").status_code == 200  # the docs page, no key needed


def test_a_body_not_declared_json_is_415(client: TestClient) -> None:
    body = b'{"name": "x"}'
    for headers in (
        {},
        {"Content-Type": "text/plain"},
        {"Content-Type": "application/x-www-form-urlencoded"},
    ):
        problem = assert_problem(
            client.post("/v1/rooms", content=body, headers={**ADMIN, **headers}), 415
        )
        assert "Content-Type: application/json" in problem["detail"]
        assert problem["errors"][0]["field"] == "header.content-type"
    declared = {**ADMIN, "Content-Type": "application/json; charset=utf-8"}
    assert client.post("/v1/rooms", json=small_room(), headers=declared).status_code == 201
    # No body at all is still a 422 naming the missing body.
    problem = assert_problem(client.post("/v1/rooms", headers=ADMIN), 422)
    assert problem["errors"][0]["field"] == "body"


def test_malformed_json_names_the_body_and_the_offset(client: TestClient) -> None:
    headers = {**ADMIN, "Content-Type": "application/json"}
    answer = client.post("/v1/rooms", content=b'{"name": "x",, }', headers=headers)
    problem = assert_problem(answer, 422)
    assert problem["errors"][0]["field"] == "body"
    assert "not valid JSON at character 13" in problem["errors"][0]["message"]


def test_if_none_match_on_a_room(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN)
    etag = room.headers["etag"]
    path = f"/v1/rooms/{room.json()['id']}"
    unchanged = client.get(path, headers={**TERMINAL, "If-None-Match": etag})
    assert unchanged.status_code == 304 and unchanged.content == b""
    assert unchanged.headers["etag"] == etag
    assert client.get(path, headers={**TERMINAL, "If-None-Match": '"other"'}).status_code == 200
    put = client.put(path, json=small_room("New"), headers={**ADMIN, "If-Match": etag})
    changed = client.get(path, headers={**TERMINAL, "If-None-Match": etag})
    assert changed.status_code == 200 and changed.headers["etag"] == put.headers["etag"] != etag


def test_202_answers_say_when_to_poll(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    rebuild = client.post(f"/v1/rooms/{room['id']}/fingerprints", headers=ADMIN)
    assert rebuild.status_code == 202
    assert rebuild.headers["retry-after"] == "1"
    assert rebuild.headers["location"] == f"/v1/jobs/{rebuild.json()['id']}"
    calibration = client.post(
        f"/v1/rooms/{room['id']}/calibrations", json={"masked_leds": [0]}, headers=ADMIN
    )
    assert calibration.status_code == 202, calibration.text
    assert calibration.headers["retry-after"] == "1"


def test_an_epoch_measurement_says_when_the_window_closes(
    tmp_path: Path, database_url: str
) -> None:
    client = start(tmp_path / "data", database_url)
    try:
        epoch = create(client, room_of(client), window_s=60)
        answer = post(client, epoch, "t1", [1e-6] * 16)
        assert answer.status_code == 202, answer.text
        # 60 s window, just opened: between 1 s and 60 s remain (never 0, never more).
        assert 1 <= int(answer.headers["retry-after"]) <= 60
    finally:
        client.__exit__(None, None, None)


def test_metrics_include_process_metrics(client: TestClient) -> None:
    text = client.get("/metrics").text
    for name in ("process_cpu_seconds_total", "process_resident_memory_bytes", "python_info"):
        assert name in text, name
