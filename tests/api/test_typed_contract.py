"""The OpenAPI document tells the truth: problem examples of their own status, typed answers,
``servers`` and one version number.

Generated clients (and Swagger UI) show what the document says; a 401 documented with a 422
body, or a room layout documented as a free-form object, misleads them.
"""

from __future__ import annotations

import json
import tomllib
from importlib.metadata import version as package_version
from pathlib import Path
from typing import Any

from app.cli import openapi_document
from app.client import VLPClient
from app.schemas import Measurement, Problem, RoomLayout
from app.schemas.rooms import paper_room_example

from .conftest import ADMIN, ADMIN_KEY, TERMINAL, TestClient

REPO = Path(__file__).resolve().parents[2]
PROBLEM = "application/problem+json"


def served() -> dict[str, Any]:
    document: dict[str, Any] = json.loads(openapi_document())
    return document


def problem_examples(document: dict[str, Any]) -> list[tuple[str, str, int, dict[str, Any]]]:
    """(path, method, status, example) of every documented problem answer."""
    found = []
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            for status, answer in operation["responses"].items():
                content = answer.get("content", {})
                if PROBLEM in content:
                    found.append((path, method, int(status), content[PROBLEM].get("example", {})))
    return found


def test_every_problem_answer_has_an_example_of_its_own_status() -> None:
    examples = problem_examples(served())
    statuses = {status for _, _, status, _ in examples}
    assert {401, 403, 404, 409, 412, 413, 422, 428, 503} <= statuses
    for path, method, status, example in examples:
        assert example.get("status") == status, (path, method, status, example)
        Problem.model_validate(example)
        assert ("errors" in example) == (status == 422), (path, method, status)


def documented(status: int) -> dict[str, Any]:
    """The example the document shows for ``status`` (the same on every operation)."""
    bodies = {
        json.dumps(example, sort_keys=True)
        for _, _, code, example in problem_examples(served())
        if code == status
    }
    assert len(bodies) == 1, bodies
    example: dict[str, Any] = json.loads(bodies.pop())
    return example


def assert_like_documented(answer: Any, status: int) -> None:
    assert answer.status_code == status, answer.text
    body = answer.json()
    example = documented(status)
    assert (body["type"], body["title"]) == (example["type"], example["title"])
    assert set(example) - {"errors"} <= set(body)


def test_real_problem_answers_match_their_documented_examples(client: TestClient) -> None:
    layout = paper_room_example()
    assert_like_documented(client.get("/v1/rooms"), 401)
    assert_like_documented(client.post("/v1/rooms", json=layout, headers=TERMINAL), 403)
    assert_like_documented(client.get("/v1/rooms/nope", headers=ADMIN), 404)
    created = client.post("/v1/rooms", json=layout, headers=ADMIN)
    room_id = created.json()["id"]
    measurement = {"power": [1.0] * 16, "targets": 1}
    # No build workers in this app: the room has no fingerprint yet.
    assert_like_documented(
        client.post(f"/v1/rooms/{room_id}/localize", json=measurement, headers=TERMINAL), 409
    )
    assert_like_documented(client.put(f"/v1/rooms/{room_id}", json=layout, headers=ADMIN), 428)
    stale = {**ADMIN, "If-Match": '"999"'}
    assert_like_documented(client.put(f"/v1/rooms/{room_id}", json=layout, headers=stale), 412)
    too_large = b"[" + b"0," * (9 * 1024 * 1024) + b"0]"
    assert_like_documented(
        client.post(
            "/v1/rooms",
            content=too_large,
            headers={**ADMIN, "Content-Type": "application/json"},
        ),
        413,
    )
    assert_like_documented(client.post("/v1/rooms", json={"name": ""}, headers=ADMIN), 422)


def component(document: dict[str, Any], name: str) -> dict[str, Any]:
    schemas: dict[str, Any] = document["components"]["schemas"]
    return dict(schemas[name])


def test_layout_and_measurement_answers_are_typed_in_the_document() -> None:
    document = served()
    room = component(document, "Room")["properties"]["layout"]
    simulation = component(document, "Simulation")["properties"]["measurement"]
    assert room["$ref"] == "#/components/schemas/RoomLayout"
    assert simulation["$ref"] == "#/components/schemas/Measurement"


def test_the_answers_parse_into_the_typed_models_with_the_same_json(
    ready_app: tuple[TestClient, str],
) -> None:
    http, room_id = ready_app
    with VLPClient(api_key=ADMIN_KEY, http_client=http) as vlp:
        room = vlp.get_room(room_id)
        simulation = vlp.simulate(room_id, targets=2, seed=3)
    assert isinstance(room.layout, RoomLayout)
    assert len(room.layout.leds) == 16 and room.layout.leds[0].z == 3.0  # defaults applied
    assert isinstance(simulation.measurement, Measurement)

    raw = http.post(
        f"/v1/rooms/{room_id}/simulate", json={"targets": 2, "seed": 3}, headers=TERMINAL
    ).json()
    # On the wire the measurement is still the body to send: only the fields it needs.
    assert sorted(raw["measurement"]) == [
        "correlation",
        "fingerprint_version",
        "model",
        "solver",
        "targets",
    ]
    assert raw["truth"][0]["terminal_id"] is None  # other nulls are kept
    assert (
        simulation.measurement.model_dump(mode="json", exclude_unset=True) == (raw["measurement"])
    )
    room_json = http.get(f"/v1/rooms/{room_id}", headers=ADMIN).json()
    assert room.layout.model_dump(mode="json") == room_json["layout"]


def test_servers_and_one_version_number() -> None:
    document = served()
    assert document["servers"] == [{"url": "/", "description": "this server"}]
    declared = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    assert document["info"]["version"] == declared["project"]["version"]
    assert package_version("vlp-service") == declared["project"]["version"]
