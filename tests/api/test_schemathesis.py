"""Property-based API tests: schemathesis drives every operation of the served OpenAPI document.

Positive and negative data, a fixed seed and a bounded example budget (the whole module runs
in well under three minutes on two cores). Every answer must be documented: no 5xx, and each
status code, content type, header and body must match the document.

The app's lifespan is owned by one starlette ``TestClient`` (one registry, one worker pool);
schemathesis only generates the requests and validates the answers, so the lifespan is never
run twice for the same app.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from schemathesis import GenerationMode
from schemathesis.checks import negative_data_rejection
from schemathesis.config import HealthCheck, PositiveDataAcceptanceConfig
from schemathesis.core.parameters import ParameterLocation

from app.main import create_app

from .conftest import ADMIN_KEY, TERMINAL_KEY, TestClient, make_settings, small_room, wait_for_room

# Slow (a minute of fuzzing), and serial: under pytest-xdist the cases of a schemathesis
# parametrization share one node id and only the first would run.
pytestmark = [pytest.mark.slow, pytest.mark.serial]
ApiCase = schemathesis.Case[schemathesis.APIOperation[Any, Any, Any, Any]]
SEED = 20261122
# Examples per operation and generation mode: about 35 s for the module on two cores.
MAX_EXAMPLES = 100
# Small limits so a generated room never starts a long build in the background.
_LIMITS: dict[str, Any] = {"max_leds": 32, "max_grid_points": 2_500}
_ROOM_PATH = "/v1/rooms/{room_id}"


@pytest.fixture(scope="module")
def fuzzed_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str]]:
    """The app with its demo room built (so localize and downloads answer 200 too)."""
    settings = make_settings(
        tmp_path_factory.mktemp("fuzz"), demo=True, embedded_workers=1, **_LIMITS
    )
    with TestClient(create_app(settings)) as client:
        room_id = client.get("/v1/rooms", headers={"X-API-Key": ADMIN_KEY}).json()["items"][0]["id"]
        wait_for_room(client, room_id)
        yield client, room_id


def _schema(*, key: str, modes: list[GenerationMode], max_examples: int) -> schemathesis.BaseSchema:
    """The app's OpenAPI document as a schemathesis schema: seeded, keyed requests.

    The document needs no lifespan, so it is read from a fresh app at collection time (routes
    added later are covered without editing this module).
    """
    document = create_app(make_settings(Path("unused"))).openapi()
    schema = schemathesis.openapi.from_dict(document)
    schema.config.seed = SEED
    schema.config.generation.update(
        modes=modes,
        max_examples=max_examples,
        deterministic=True,
        with_security_parameters=False,
    )
    # Hypothesis' too_slow health check fails a test whose data generation took too long on
    # the clock: on a loaded machine that is the machine, not the API (its CI profile
    # suppresses it too; ./test runs outside CI as well).
    schema.config.update(headers={"X-API-Key": key}, suppress_health_check=[HealthCheck.too_slow])
    # Nothing is written into the repository (schemathesis' cache lives in .schemathesis/
    # of the working directory) and no run starts from what an earlier run left there.
    schema.config.cache.enabled = False
    # A schema-valid request may still be refused for what JSON Schema cannot say: a stale
    # If-Match (412) or none (428), cross-field rules such as a grid step that must divide
    # the room, a vector of M numbers, a cursor the server never issued (422). Those answers
    # must still be documented problems, which the other checks assert.
    schema.config.checks.positive_data_acceptance = PositiveDataAcceptanceConfig(
        expected_statuses=["2xx", "3xx", 401, 403, 404, 409, 412, 422, 428, 429, "5xx"]
    )
    # `ignored_auth` would replay requests through schemathesis' own ASGI client, which runs
    # a second lifespan of the app; test_security.py's route x role matrix covers auth.
    schema.config.checks.update(excluded_check_names=["ignored_auth"])
    return schema


_BOTH = [GenerationMode.POSITIVE, GenerationMode.NEGATIVE]
# As the admin; room deletion is fuzzed only on generated ids (the demo room must stay).
admin_schema = _schema(key=ADMIN_KEY, modes=_BOTH, max_examples=MAX_EXAMPLES)
# Read-only pass as a terminal: reads answer, writes are refused (403), all documented.
terminal_schema = _schema(key=TERMINAL_KEY, modes=[GenerationMode.POSITIVE], max_examples=8)


def _pin_room(case: ApiCase, room_id: str, scratch_id: str) -> None:
    """Aim the case at a real room, unless its path parameters were generated to be invalid.

    Generated room ids (mostly unknown: 404) are kept for room deletion, for invalid path
    data and for every third example, so unknown ids are fuzzed too. Replacements go to the
    scratch room with `If-Match: *` (unless the headers were generated to be invalid), so
    that they can succeed without touching the demo room's layout.
    """
    path = case.path_parameters
    if not path or "room_id" not in path:
        return
    components = case.meta.components if case.meta else {}
    if _negative(components.get(ParameterLocation.PATH)):
        return
    if case.method == "DELETE" and case.path == _ROOM_PATH:
        return
    if zlib.crc32(str(path["room_id"]).encode()) % 3 == 0:
        return
    if case.method == "PUT":
        path["room_id"] = scratch_id
        if not _negative(components.get(ParameterLocation.HEADER)):
            case.headers["If-Match"] = "*"
        return
    path["room_id"] = room_id


def _negative(component: Any) -> bool:
    return component is not None and component.mode is GenerationMode.NEGATIVE


def _send(client: TestClient, case: ApiCase) -> Any:
    """Send the generated request through the app's own test client (its live lifespan)."""
    kwargs = case.as_transport_kwargs(base_url="http://testserver")
    # The API has no cookie parameters; per-request cookies are deprecated in httpx anyway.
    assert not kwargs.get("cookies"), kwargs
    content = kwargs.get("data")
    if isinstance(content, str):
        content = content.encode()
    return client.request(
        kwargs["method"],
        kwargs["url"],
        params=kwargs.get("params"),
        headers=kwargs.get("headers"),
        json=kwargs.get("json"),
        content=content if isinstance(content, bytes) else None,
        data=content if isinstance(content, dict) else None,
    )


# A batch answers a schema-violating *item* with a problem in its place, not a 4xx for the
# whole request (API.md): the other items are still solved. Every other check still applies
# to it (documented status, answer schema); tests/api/test_localize_batch.py asserts the
# item problems themselves.
_ITEMS_ANSWERED_ONE_BY_ONE = "/v1/rooms/{room_id}/localize/batch"


# An event stream never ends: its 200 is checked by its headers (tests/api/test_tracks.py
# reads its events); its refusals are whole problem answers, checked as any other.
_ENDLESS = "/v1/rooms/{room_id}/tracks/stream"


def _check_stream(client: TestClient, case: ApiCase) -> None:
    kwargs = case.as_transport_kwargs(base_url="http://testserver")
    with client.stream(
        kwargs["method"], kwargs["url"], params=kwargs.get("params"), headers=kwargs.get("headers")
    ) as response:
        if response.status_code == 200:
            assert response.headers["content-type"].startswith("text/event-stream")
            return
        response.read()
    assert response.status_code < 500, f"{case.method} {case.formatted_path}: {response.text}"
    case.validate_response(response)


def _check(client: TestClient, case: ApiCase) -> None:
    if case.path == _ENDLESS:
        _check_stream(client, case)
        return
    response = _send(client, case)
    assert response.status_code < 500, f"{case.method} {case.formatted_path}: {response.text}"
    excluded = [negative_data_rejection] if case.path == _ITEMS_ANSWERED_ONE_BY_ONE else None
    case.validate_response(response, excluded_checks=excluded)


@pytest.fixture(scope="module")
def scratch_room(fuzzed_app: tuple[TestClient, str]) -> str:
    """A second room that fuzzed replacements may change (the demo room's layout stays)."""
    client, _ = fuzzed_app
    created = client.post("/v1/rooms", json=small_room(), headers={"X-API-Key": ADMIN_KEY})
    room_id: str = created.json()["id"]
    return room_id


@admin_schema.parametrize()
def test_admin_requests_conform(
    case: ApiCase, fuzzed_app: tuple[TestClient, str], scratch_room: str
) -> None:
    client, room_id = fuzzed_app
    _pin_room(case, room_id, scratch_room)
    _check(client, case)


@terminal_schema.parametrize()
def test_terminal_requests_conform(
    case: ApiCase, fuzzed_app: tuple[TestClient, str], scratch_room: str
) -> None:
    client, room_id = fuzzed_app
    _pin_room(case, room_id, scratch_room)
    _check(client, case)


def _all_rooms(client: TestClient) -> list[dict[str, Any]]:
    rooms: list[dict[str, Any]] = []
    cursor: str | None = None
    while True:
        params: dict[str, Any] = {"limit": 100, **({"cursor": cursor} if cursor else {})}
        page = client.get("/v1/rooms", params=params, headers={"X-API-Key": ADMIN_KEY}).json()
        rooms += page["items"]
        cursor = page["next_cursor"]
        if cursor is None:
            return rooms


def test_every_accepted_layout_builds(fuzzed_app: tuple[TestClient, str]) -> None:
    """Run after the fuzzing: a layout the API accepted must also build (none `failed`)."""
    client, _ = fuzzed_app
    rooms = _all_rooms(client)
    assert len(rooms) > 1  # the fuzzing created rooms
    for room in rooms:
        wait_for_room(client, room["id"])  # fails on a `failed` build


def test_the_fuzzing_reached_success_answers(fuzzed_app: tuple[TestClient, str]) -> None:
    """Run after the fuzzing: it got past auth and validation, not only refusals."""
    client, _ = fuzzed_app
    metrics = client.app.state.metrics  # type: ignore[attr-defined]
    answered = {
        (sample.labels["method"], sample.labels["route"], sample.labels["status"])
        for family in metrics.requests.collect()
        for sample in family.samples
        if sample.name.endswith("_total") and sample.value > 0
    }
    for method, route, status in [
        ("POST", "/v1/rooms", "201"),
        ("PUT", "/v1/rooms/{room_id}", "200"),
        ("POST", "/v1/rooms/{room_id}/localize", "200"),
        ("POST", "/v1/rooms/{room_id}/simulate", "200"),
        ("GET", "/v1/rooms/{room_id}/fingerprints/{version}/{matrix}.npy", "200"),
        ("POST", "/v1/rooms/{room_id}/localize", "422"),
        ("POST", "/v1/rooms", "403"),
    ]:
        assert (method, route, status) in answered, (method, route, status)


def test_demo_room_survives_the_fuzzing(fuzzed_app: tuple[TestClient, str]) -> None:
    """Run last in this module: the pinned room still exists and still localizes."""
    client, room_id = fuzzed_app
    headers = {"X-API-Key": TERMINAL_KEY}
    room = wait_for_room(client, room_id)
    simulated = client.post(
        f"/v1/rooms/{room_id}/simulate", json={"targets": 2, "seed": 1}, headers=headers
    )
    assert simulated.status_code == 200, simulated.text
    located = client.post(
        f"/v1/rooms/{room_id}/localize", json=simulated.json()["measurement"], headers=headers
    )
    assert located.status_code == 200, located.text
    assert located.json()["fingerprint_version"] == room["fingerprint"]["version"]
