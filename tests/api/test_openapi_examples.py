"""Every request body in the OpenAPI document has an example that works on the demo room.

Swagger UI fills "Try it out" with the first example; these tests keep that a working call.
"""

from __future__ import annotations

import functools
import json
import math
import re
from collections.abc import Iterator
from typing import Any

import jsonschema_rs
import pytest

from app.cli import openapi_document
from app.schemas.localize import EXAMPLE_POSITIONS_M

from .conftest import ADMIN, TestClient

_METHODS = ("get", "put", "post", "patch", "delete")
_PATH_PARAMETER = re.compile(r"\{([^}]+)\}")


@functools.cache
def _document() -> dict[str, Any]:
    """The served document (read only)."""
    document: dict[str, Any] = json.loads(openapi_document())
    return document


def _resolve(document: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        node: Any = document
        for part in schema["$ref"].removeprefix("#/").split("/"):
            node = node[part]
        schema = node
    return schema


def _examples(document: dict[str, Any], media: dict[str, Any]) -> list[Any]:
    """The examples of one request media type: its own, else its schema's."""
    if "example" in media:
        return [media["example"]]
    if "examples" in media:
        return [_resolve(document, item).get("value") for item in media["examples"].values()]
    schema = _resolve(document, media.get("schema", {}))
    if "examples" in schema:
        return list(schema["examples"])
    return [schema["example"]] if "example" in schema else []


def _request_bodies() -> Iterator[tuple[str, str, str, dict[str, Any]]]:
    document = _document()
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            if method in _METHODS and "requestBody" in operation:
                for media_type, media in operation["requestBody"]["content"].items():
                    yield method, path, media_type, media


BODIES = list(_request_bodies())


def test_the_document_has_the_known_request_bodies() -> None:
    seen = {(method, path) for method, path, _, _ in BODIES}
    assert {
        ("post", "/v1/rooms"),
        ("put", "/v1/rooms/{room_id}"),
        ("post", "/v1/rooms/{room_id}/simulate"),
        ("post", "/v1/rooms/{room_id}/localize"),
    } <= seen


@pytest.mark.parametrize(
    ("method", "path", "media_type", "media"),
    BODIES,
    ids=[f"{method} {path} {media_type}" for method, path, media_type, _ in BODIES],
)
def test_every_request_body_has_examples_that_fit_its_schema(
    method: str, path: str, media_type: str, media: dict[str, Any]
) -> None:
    document = _document()
    examples = _examples(document, media)
    assert examples, f"{method.upper()} {path} ({media_type}) has no example"
    # Validate against the published schema itself (refs resolved within the document).
    schema = {**media["schema"], "components": document["components"]}
    validator = jsonschema_rs.Draft202012Validator(schema)
    for example in examples:
        errors = [error.message for error in validator.iter_errors(example)]
        assert not errors, f"{method.upper()} {path}: example {example!r} is invalid: {errors}"


def _call_with_example(
    client: TestClient, room_id: str, method: str, path: str, example: Any
) -> int:
    headers = dict(ADMIN)
    if method == "put" and path == "/v1/rooms/{room_id}":
        headers["If-Match"] = client.get(f"/v1/rooms/{room_id}", headers=ADMIN).headers["ETag"]
    url = path.replace("{room_id}", room_id)
    status: int = client.request(method.upper(), url, json=example, headers=headers).status_code
    return status


def test_the_first_example_of_each_body_is_accepted_by_the_app(
    ready_app: tuple[TestClient, str],
) -> None:
    """What "Try it out" sends by default succeeds on the demo room.

    Bodies of paths with other parameters than the room (e.g. an epoch id) need an object
    made first; they are covered by their own tests.
    """
    client, room_id = ready_app
    document = _document()
    called = []
    # PUT last: it replaces the demo room's layout (with the same paper room) and rebuilds.
    for method, path, _, media in sorted(BODIES, key=lambda body: body[0] == "put"):
        if set(_PATH_PARAMETER.findall(path)) - {"room_id"}:
            continue
        example = _examples(document, media)[0]
        status = _call_with_example(client, room_id, method, path, example)
        assert status < 400, f"{method.upper()} {path} with its example answered {status}"
        called.append((method, path))
    assert ("post", "/v1/rooms/{room_id}/localize") in called


def test_the_localize_example_finds_its_three_terminals(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    operation = _document()["paths"]["/v1/rooms/{room_id}/localize"]["post"]
    measurement = _examples(_document(), operation["requestBody"]["content"]["application/json"])[0]
    assert len(measurement["correlation"]) == 16
    assert all(len(row) == 16 for row in measurement["correlation"])
    # Pinned to the demo room's first build: another test here sends every example body,
    # and the calibration example (a perturbed survey) may meanwhile have made a calibrated
    # fingerprint current, on which the nominal room's example no longer fits.
    pinned = {**measurement, "fingerprint_version": 1}
    answer = client.post(f"/v1/rooms/{room_id}/localize", json=pinned, headers=ADMIN)
    assert answer.status_code == 200, answer.text
    assert answer.json()["fingerprint_version"] == 1
    estimates = [(e["x"], e["y"]) for e in answer.json()["estimates"]]
    assert len(estimates) == len(EXAMPLE_POSITIONS_M)
    for x, y in EXAMPLE_POSITIONS_M:
        nearest = min(math.hypot(x - ex, y - ey) for ex, ey in estimates)
        assert nearest < 0.1, (x, y, estimates)
