"""Hostile inputs: each gets a 4xx problem naming what is wrong, and nothing stored changes.

One app per module with two ready rooms: the paper's demo room (16 LEDs, 400 grid points)
and a small room (2 LEDs, 32 grid points). Every test compares what is stored (rooms, their
ETags, fingerprint versions with their matrices' sha256, the bytes of a downloaded H)
before and after its requests.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from app.main import create_app
from app.schemas.rooms import paper_room_example

from .conftest import (
    ADMIN,
    TERMINAL,
    TestClient,
    assert_problem,
    make_settings,
    small_room,
    wait_for_room,
)

M_DEMO = 16
N_SMALL = 32  # small_room(): 2 x 1 m at 0.25 m


@pytest.fixture(scope="module")
def rooms(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str, str]]:
    """(client, demo room id, small room id), both with a ready fingerprint."""
    settings = make_settings(tmp_path_factory.mktemp("hostile"), demo=True, embedded_workers=1)
    with TestClient(create_app(settings)) as client:
        demo = client.get("/v1/rooms", headers=ADMIN).json()["items"][0]["id"]
        small = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()["id"]
        wait_for_room(client, demo)
        wait_for_room(client, small)
        yield client, demo, small


def stored_state(client: TestClient) -> dict[str, Any]:
    """Everything a request could have changed, as the API shows it."""
    state: dict[str, Any] = {}
    for room in client.get("/v1/rooms", params={"limit": 100}, headers=ADMIN).json()["items"]:
        path = f"/v1/rooms/{room['id']}"
        read = client.get(path, headers=ADMIN)
        versions = client.get(f"{path}/fingerprints", headers=ADMIN).json()["items"]
        matrix = client.get(f"{path}/fingerprints/current/H.npy", headers=ADMIN)
        state[room["id"]] = {
            "etag": read.headers["etag"],
            "room": read.json(),
            "fingerprints": [
                (fp["version"], {name: meta["sha256"] for name, meta in fp["matrices"].items()})
                for fp in versions
            ],
            "H": hashlib.sha256(matrix.content).hexdigest(),
        }
    return state


@contextmanager
def state_unchanged(client: TestClient) -> Iterator[None]:
    """Assert that the requests made inside leave everything stored as it was."""
    before = stored_state(client)
    assert len(before) == 2
    yield
    assert stored_state(client) == before


def _post_raw(client: TestClient, path: str, content: bytes, content_type: str) -> Any:
    return client.post(path, content=content, headers={**ADMIN, "Content-Type": content_type})


# -- measurements ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "raw, fields",
    [
        (b'{"power": [NaN' + b", 1" * (M_DEMO - 1) + b"]}", ["body.power.0"]),
        (b'{"power": [1, Infinity' + b", 1" * (M_DEMO - 2) + b"]}", ["body.power.1"]),
        (b'{"correlation": [-Infinity], "targets": 1}', ["body.correlation.list[float].0"]),
        (b'{"power": [1], "targets": NaN}', ["body.targets"]),
    ],
    ids=["nan-power", "infinity-power", "minus-infinity-correlation", "nan-targets"],
)
def test_nan_and_infinity_tokens_are_refused(
    rooms: tuple[TestClient, str, str], raw: bytes, fields: list[str]
) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        response = _post_raw(client, f"/v1/rooms/{demo}/localize", raw, "application/json")
        problem = assert_problem(response, 422)
        named = {error["field"] for error in problem["errors"]}
        assert set(fields) <= named, problem


def test_nan_in_a_layout_is_refused(rooms: tuple[TestClient, str, str]) -> None:
    client, _, _ = rooms
    text = json.dumps(small_room()).replace('"length": 2.0', '"length": NaN')
    with state_unchanged(client):
        response = _post_raw(client, "/v1/rooms", text.encode(), "application/json")
        assert_problem(response, 422, ["body.room.length"])


@pytest.mark.parametrize(
    "body, field, words",
    [
        ({"power": [1.0] * 3}, "body.power", "16 entries"),
        ({"correlation": [[1.0] * 5] * 5}, "body.correlation", "16 x 16"),
        ({"correlation": [1.0] * 100}, "body.correlation", "136 upper-triangle"),
        (
            {"terminals": [{"id": "t1", "amplitudes": [1.0] * 15}]},
            "body.terminals.0.amplitudes",
            "expected 16",
        ),
    ],
    ids=["power-3", "correlation-5x5", "correlation-100", "terminal-15"],
)
def test_wrong_vector_lengths_are_refused(
    rooms: tuple[TestClient, str, str], body: dict[str, Any], field: str, words: str
) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        response = client.post(f"/v1/rooms/{demo}/localize", json=body, headers=TERMINAL)
        problem = assert_problem(response, 422, [field])
        assert words in problem["detail"]


@pytest.mark.parametrize(
    "power, words",
    [
        ([-1.0] * M_DEMO, ">= 0"),
        ([0.0] * M_DEMO, "all zero"),
        ([1e300] * M_DEMO, "at most 1e+100"),
        ([1e-300] * M_DEMO, "no pilot was received"),
    ],
    ids=["negative", "all-zero", "1e300", "1e-300"],
)
@pytest.mark.parametrize("solver", ["gridless", "nnls", "omp", "l1"])
def test_impossible_powers_are_refused(
    rooms: tuple[TestClient, str, str], power: list[float], words: str, solver: str
) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        body = {"power": power, "solver": solver}
        response = client.post(f"/v1/rooms/{demo}/localize", json=body, headers=TERMINAL)
        problem = assert_problem(response, 422, ["body.power"])
        assert words in problem["detail"]


def test_huge_terminal_amplitudes_are_refused_naming_terminals(
    rooms: tuple[TestClient, str, str],
) -> None:
    client, demo, _ = rooms
    body = {"terminals": [{"id": "t1", "amplitudes": [1e200] * M_DEMO}]}
    with state_unchanged(client):
        response = client.post(f"/v1/rooms/{demo}/localize", json=body, headers=TERMINAL)
        assert_problem(response, 422, ["body.terminals"])


@pytest.mark.parametrize(
    "targets, room, words",
    [
        (0, "demo", "greater than or equal to 1"),
        (-3, "demo", "greater than or equal to 1"),
        (65, "demo", "less than or equal to 64"),
        (N_SMALL + 1, "small", "between 1 and 32"),
    ],
    ids=["zero", "negative", "over-64", "over-N"],
)
def test_targets_out_of_range_are_refused(
    rooms: tuple[TestClient, str, str], targets: int, room: str, words: str
) -> None:
    client, demo, small = rooms
    room_id, n_leds = (demo, M_DEMO) if room == "demo" else (small, 2)
    with state_unchanged(client):
        body = {"power": [1e-9] * n_leds, "targets": targets, "solver": "nnls"}
        response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
        problem = assert_problem(response, 422, ["body.targets"])
        assert words in problem["detail"]
        simulated = client.post(
            f"/v1/rooms/{room_id}/simulate", json={"targets": targets}, headers=TERMINAL
        )
        assert_problem(simulated, 422, ["body.targets"])


def test_unknown_solver_is_refused(rooms: tuple[TestClient, str, str]) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        body = {"power": [1.0] * M_DEMO, "solver": "../../bin/sh"}
        response = client.post(f"/v1/rooms/{demo}/localize", json=body, headers=TERMINAL)
        problem = assert_problem(response, 422, ["body.solver"])
        assert "gridless" in problem["detail"]


@pytest.mark.parametrize(
    "body, fields",
    [
        ({}, ["body.power", "body.correlation", "body.terminals"]),
        ({"targets": 2}, ["body.power", "body.correlation", "body.terminals"]),
        ({"power": [1.0] * M_DEMO, "correlation": [1.0] * 136}, ["body.power", "body.correlation"]),
        (
            {"terminals": [{"id": "t1", "amplitudes": [1.0] * M_DEMO}] * 2},
            ["body.terminals.1.id"],
        ),
        ({"power": [1.0] * M_DEMO, "powers": [1.0]}, ["body.powers"]),
    ],
    ids=["empty", "no-measurement", "power-and-correlation", "same-terminal-twice", "typo-field"],
)
def test_missing_or_doubled_measurement_fields_are_refused(
    rooms: tuple[TestClient, str, str], body: dict[str, Any], fields: list[str]
) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        response = client.post(f"/v1/rooms/{demo}/localize", json=body, headers=TERMINAL)
        assert_problem(response, 422, fields)


# -- layouts --------------------------------------------------------------------------------


def _layout_with(path: str, value: Any) -> dict[str, Any]:
    """The paper layout with one field (``"leds.0.z"``) set to ``value``."""
    layout = copy.deepcopy(paper_room_example())
    *parents, last = path.split(".")
    target: Any = layout
    for part in parents:
        target = target[int(part)] if part.isdigit() else target[part]
    target[last] = value
    return layout


_BAD_LAYOUTS = [
    ("room.length", 0.0, "zero-length"),
    ("room.width", -4.0, "negative-width"),
    ("room.height", 0.0, "zero-height"),
    ("grid.step", 0.0, "zero-step"),
    ("grid.step", -0.2, "negative-step"),
    ("grid.step", 0.3, "step-not-dividing"),
    ("grid.step", 1e-5, "step-1.6e11-points"),
    ("leds.3.x", 4.5, "led-outside-x"),
    ("leds.3.y", -0.1, "led-outside-y"),
    ("leds.3.z", 3.5, "led-above-ceiling"),
    ("leds.3.z", 0.5, "led-below-receivers"),
    ("receiver.fov_deg", 0.0, "fov-zero"),
    ("receiver.fov_deg", 91.0, "fov-over-90"),
    ("receiver.fov_deg", 1e-300, "fov-tiny"),
    ("leds.0.half_power_angle_deg", 90.0, "beam-90"),
    ("leds.0.half_power_angle_deg", -10.0, "beam-negative"),
    ("leds.0.pilot_amplitude", 0.0, "amplitude-zero"),
    ("leds.0.pilot_amplitude", 1e300, "amplitude-1e300"),
]


@pytest.mark.parametrize(
    "path, value", [case[:2] for case in _BAD_LAYOUTS], ids=[case[2] for case in _BAD_LAYOUTS]
)
@pytest.mark.parametrize("method", ["POST", "PUT"])
def test_impossible_layouts_are_refused(
    rooms: tuple[TestClient, str, str], path: str, value: Any, method: str
) -> None:
    client, demo, _ = rooms
    body = _layout_with(path, value)
    with state_unchanged(client):
        if method == "POST":
            response = client.post("/v1/rooms", json=body, headers=ADMIN)
        else:  # with the right ETag: only the layout stands in the way
            etag = client.get(f"/v1/rooms/{demo}", headers=ADMIN).headers["etag"]
            headers = {**ADMIN, "If-Match": etag}
            response = client.put(f"/v1/rooms/{demo}", json=body, headers=headers)
        assert_problem(response, 422, [f"body.{path}"])


def test_grid_of_1e11_points_says_how_many(rooms: tuple[TestClient, str, str]) -> None:
    client, _, _ = rooms
    with state_unchanged(client):
        body = _layout_with("grid.step", 1e-5)
        problem = assert_problem(client.post("/v1/rooms", json=body, headers=ADMIN), 422)
        assert "1.6e+11" in problem["detail"] and "1000000" in problem["detail"]


def test_20000_leds_are_refused(rooms: tuple[TestClient, str, str]) -> None:
    client, _, _ = rooms
    leds = [{"x": (i % 200) * 0.02, "y": (i // 200) * 0.04} for i in range(20_000)]
    body = {**paper_room_example(), "leds": leds}
    with state_unchanged(client):
        problem = assert_problem(client.post("/v1/rooms", json=body, headers=ADMIN), 422)
        assert problem["errors"] == [
            {"field": "body.leds", "message": "at most 4096 LEDs are allowed, got 20000"}
        ]


# -- bodies and paths -----------------------------------------------------------------------


def test_64_mib_body_is_413(rooms: tuple[TestClient, str, str]) -> None:
    client, demo, _ = rooms
    body = b'{"power": [' + b"1.0, " * (64 * 1024 * 1024 // 5) + b"1.0]}"
    with state_unchanged(client):
        for path in ("/v1/rooms", f"/v1/rooms/{demo}/localize"):
            problem = assert_problem(_post_raw(client, path, body, "application/json"), 413)
            assert problem["type"] == "urn:vlp:problem:payload-too-large"


@pytest.mark.parametrize(
    "content, content_type",
    [
        (b"hello", "text/plain"),
        (b"{broken", "application/json"),
        (b"\xff\xfe\x00garbage", "application/json"),
        (b"name=room", "application/x-www-form-urlencoded"),
        (b"", "application/json"),
        (b"[1, 2]", "application/json"),
        (b'"a string"', "application/json"),
        (b"[" * 100_000, "application/json"),
        (b'{"name": ' + b"9" * 5000 + b"}", "application/json"),
    ],
    ids=["text", "broken-json", "not-utf8", "form", "empty", "array", "string", "deep", "long-int"],
)
@pytest.mark.parametrize("target", ["rooms", "localize"])
def test_non_json_bodies_are_refused(
    rooms: tuple[TestClient, str, str], content: bytes, content_type: str, target: str
) -> None:
    client, demo, _ = rooms
    path = "/v1/rooms" if target == "rooms" else f"/v1/rooms/{demo}/localize"
    # A body not declared JSON is a 415 naming the header; a JSON one that is not the
    # right JSON is a 422 naming the body.
    declared_json = content_type == "application/json"
    with state_unchanged(client):
        answer = _post_raw(client, path, content, content_type)
        problem = assert_problem(answer, 422 if declared_json else 415)
        prefix = "body" if declared_json else "header.content-type"
        assert problem["errors"] and all(e["field"].startswith(prefix) for e in problem["errors"])


@pytest.mark.parametrize(
    "suffix",
    [
        "/fingerprints/current/..%2F..%2F..%2Fregistry.sqlite3.npy",
        "/fingerprints/current/%2E%2E%2Fcredentials.npy",
        "/fingerprints/..%2F..%2F..%2Fetc%2Fpasswd/H.npy",
        "/fingerprints/current/H.npy%00.txt",
        "/fingerprints/1/..%5C..%5Cpsi.npy",
    ],
)
def test_path_traversal_in_matrix_names_is_refused(
    rooms: tuple[TestClient, str, str], suffix: str
) -> None:
    client, demo, _ = rooms
    with state_unchanged(client):
        for room_part in (demo, "..%2F..%2Fetc"):
            response = client.get(f"/v1/rooms/{room_part}{suffix}", headers=ADMIN)
            assert 400 <= response.status_code < 500, response.text
            assert response.headers["content-type"] == "application/problem+json"
            assert b"SQLite format" not in response.content and b"root:" not in response.content
            assert b"VLP_ADMIN_KEYS" not in response.content


@pytest.mark.parametrize(
    "method, path",
    [
        ("GET", "/v1/rooms/{unknown}"),
        ("DELETE", "/v1/rooms/{unknown}"),
        ("GET", "/v1/rooms/{unknown}/fingerprints"),
        ("GET", "/v1/rooms/{demo}/fingerprints/999"),
        ("GET", "/v1/rooms/{demo}/fingerprints/999/H.npy"),
        ("POST", "/v1/rooms/{unknown}/fingerprints"),
        ("GET", "/v1/jobs/{unknown}"),
        ("POST", "/v1/rooms/{unknown}/localize"),
        ("POST", "/v1/rooms/{unknown}/simulate"),
    ],
)
def test_unknown_ids_are_404(rooms: tuple[TestClient, str, str], method: str, path: str) -> None:
    client, demo, _ = rooms
    unknown = "0123456789abcdef0123456789abcdef"
    url = path.format(unknown=unknown, demo=demo)
    body = {"power": [1.0] * M_DEMO} if url.endswith("/localize") else {"targets": 1}
    with state_unchanged(client):
        response = client.request(
            method, url, json=body if method == "POST" else None, headers=ADMIN
        )
        problem = assert_problem(response, 404)
        assert unknown in problem["detail"] or "999" in problem["detail"]


def test_put_to_unknown_room_is_404(rooms: tuple[TestClient, str, str]) -> None:
    client, _, _ = rooms
    with state_unchanged(client):
        headers = {**ADMIN, "If-Match": "*"}
        response = client.put("/v1/rooms/nope", json=small_room(), headers=headers)
        assert_problem(response, 404)
