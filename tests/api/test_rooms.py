"""Rooms: CRUD, ETag/If-Match, pagination and validation problems naming fields."""

from __future__ import annotations

import copy
import tracemalloc
from typing import Any

import pytest

import app.services.rooms
from app.schemas.rooms import paper_room_example
from app.vlp.layout_mapping import layout_from_mapping

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, make_settings, small_room


def test_create_applies_defaults_and_answers_location_and_etag(client: TestClient) -> None:
    response = client.post("/v1/rooms", json=small_room(), headers=ADMIN)
    assert response.status_code == 201, response.text
    room = response.json()
    assert response.headers["location"] == f"/v1/rooms/{room['id']}"
    assert response.headers["etag"] == f'"{room["id"]}-1"'
    assert room["layout_version"] == 1
    assert room["fingerprint"]["status"] == "pending"
    assert room["fingerprint"]["version"] is None
    assert room["fingerprint"]["job_id"]
    # Defaults of the contract: receiver as documented, LED z = room height.
    assert room["layout"]["receiver"] == {
        "area": 1e-4,
        "fov_deg": 70.0,
        "filter_gain": 1.0,
        "refractive_index": 1.5,
    }
    assert room["layout"]["leds"][0] == {
        "x": 0.5,
        "y": 0.5,
        "z": 2.5,
        "half_power_angle_deg": 60.0,
        "pilot_amplitude": 1.0,
        "normal": [0.0, 0.0, -1.0],
        "beam": None,
    }
    stored = layout_from_mapping(small_room()).to_mapping()
    # The answer also shows the optional real-room fields with their defaults (line of
    # sight only, every receiver on the plane); the stored mapping leaves them out.
    stored["room"] = {**stored["room"], "reflectance": None}
    stored["leds"] = [{**led, "normal": [0.0, 0.0, -1.0], "beam": None} for led in stored["leds"]]
    stored["grid"] = {
        **stored["grid"],
        "receiver_height_sd": 0.0,
        "receiver_tilt_sd": 0.0,
        "receivers_level": False,
    }
    assert room["layout"] == stored
    got = client.get(f"/v1/rooms/{room['id']}", headers=TERMINAL)
    assert got.status_code == 200
    assert got.json() == room
    assert got.headers["etag"] == response.headers["etag"]
    job = client.get(f"/v1/jobs/{room['fingerprint']['job_id']}", headers=TERMINAL).json()
    assert job["room_id"] == room["id"] and job["status"] == "queued" and job["result"] is None


def test_paper_room_example_is_accepted(client: TestClient) -> None:
    response = client.post("/v1/rooms", json=paper_room_example(), headers=ADMIN)
    assert response.status_code == 201, response.text
    assert len(response.json()["layout"]["leds"]) == 16


def test_replace_needs_current_etag(client: TestClient) -> None:
    created = client.post("/v1/rooms", json=small_room(), headers=ADMIN)
    room_id, etag = created.json()["id"], created.headers["etag"]
    changed = small_room("Renamed", leds=[{"x": 1.0, "y": 0.5, "z": 2.0}])

    assert_problem(client.put(f"/v1/rooms/{room_id}", json=changed, headers=ADMIN), 428)
    stale = {**ADMIN, "If-Match": f'"{room_id}-7"'}
    assert_problem(client.put(f"/v1/rooms/{room_id}", json=changed, headers=stale), 412)

    replaced = client.put(f"/v1/rooms/{room_id}", json=changed, headers={**ADMIN, "If-Match": etag})
    assert replaced.status_code == 200, replaced.text
    body = replaced.json()
    assert body["layout_version"] == 2 and body["name"] == "Renamed"
    assert body["layout"]["leds"] == [
        {
            "x": 1.0,
            "y": 0.5,
            "z": 2.0,
            "half_power_angle_deg": 60.0,
            "pilot_amplitude": 1.0,
            "normal": [0.0, 0.0, -1.0],
            "beam": None,
        }
    ]
    assert replaced.headers["etag"] == f'"{room_id}-2"' != etag
    # The old ETag is now stale.
    again = client.put(f"/v1/rooms/{room_id}", json=changed, headers={**ADMIN, "If-Match": etag})
    assert_problem(again, 412)


def test_replace_and_delete_unknown_room_are_404(client: TestClient) -> None:
    headers = {**ADMIN, "If-Match": '"x-1"'}
    assert_problem(client.put("/v1/rooms/nope", json=small_room(), headers=headers), 404)
    assert_problem(client.delete("/v1/rooms/nope", headers=ADMIN), 404)
    assert_problem(client.get("/v1/rooms/nope", headers=ADMIN), 404)


def test_delete_removes_room_and_its_jobs(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    response = client.delete(f"/v1/rooms/{room['id']}", headers=ADMIN)
    assert response.status_code == 204 and response.content == b""
    assert_problem(client.get(f"/v1/rooms/{room['id']}", headers=ADMIN), 404)
    assert_problem(client.get(f"/v1/jobs/{room['fingerprint']['job_id']}", headers=ADMIN), 404)
    assert client.get("/v1/rooms", headers=ADMIN).json()["items"] == []


def test_pagination_walks_every_room_once_in_creation_order(client: TestClient) -> None:
    ids = [
        client.post("/v1/rooms", json=small_room(f"room {index}"), headers=ADMIN).json()["id"]
        for index in range(5)
    ]
    seen: list[str] = []
    cursor = None
    pages = 0
    while True:
        params: dict[str, Any] = {"limit": 2} | ({"cursor": cursor} if cursor else {})
        page = client.get("/v1/rooms", params=params, headers=TERMINAL).json()
        assert len(page["items"]) <= 2
        seen += [room["id"] for room in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids
    assert pages == 3
    default = client.get("/v1/rooms", headers=TERMINAL).json()
    assert [room["id"] for room in default["items"]] == ids and default["next_cursor"] is None


@pytest.mark.parametrize(
    "params, field",
    [
        ({"limit": 0}, "query.limit"),
        ({"limit": 101}, "query.limit"),
        ({"limit": "many"}, "query.limit"),
        ({"cursor": "not-a-cursor"}, "query.cursor"),
    ],
    ids=["zero", "above-100", "not-int", "bad-cursor"],
)
def test_bad_page_parameters_are_422(
    client: TestClient, params: dict[str, Any], field: str
) -> None:
    client.post("/v1/rooms", json=small_room(), headers=ADMIN)
    problem = assert_problem(client.get("/v1/rooms", params=params, headers=ADMIN), 422)
    assert [error["field"] for error in problem["errors"]] == [field]


def _with(path: str, value: Any) -> dict[str, Any]:
    body = copy.deepcopy(small_room())
    target: Any = body
    keys = path.split(".")
    for key in keys[:-1]:
        target = target[int(key)] if key.isdigit() else target[key]
    last = keys[-1]
    if value is _DELETE:
        del target[last]
    elif last.isdigit():
        target[int(last)] = value
    else:
        target[last] = value
    return body


_DELETE = object()


@pytest.mark.parametrize(
    "path, value, field",
    [
        ("room.length", -1.0, "body.room.length"),
        ("room.height", 0, "body.room.height"),
        ("grid.step", "wide", "body.grid.step"),
        ("grid.step", 0.3, "body.grid.step"),
        ("grid.receiver_height", 2.5, "body.grid.receiver_height"),
        ("receiver", {"fov_deg": 120}, "body.receiver.fov_deg"),
        ("receiver", {"refractive_index": 0.5}, "body.receiver.refractive_index"),
        ("leds.1.z", 3.0, "body.leds.1.z"),
        ("leds.1.z", 0.5, "body.leds.1.z"),
        ("leds.0.x", 2.5, "body.leds.0.x"),
        ("leds.0.half_power_angle_deg", 90, "body.leds.0.half_power_angle_deg"),
        ("leds.0.pilot_amplitude", 0, "body.leds.0.pilot_amplitude"),
        ("leds", [], "body.leds"),
        ("name", _DELETE, "body.name"),
        ("colour", "red", "body.colour"),
    ],
    ids=lambda value: str(value) if isinstance(value, str) else None,
)
def test_invalid_layout_names_the_field(
    client: TestClient, path: str, value: Any, field: str
) -> None:
    response = client.post("/v1/rooms", json=_with(path, value), headers=ADMIN)
    problem = assert_problem(response, 422)
    assert field in [error["field"] for error in problem["errors"]], problem
    assert client.get("/v1/rooms", headers=ADMIN).json()["items"] == []


def test_tiny_grid_step_is_refused_before_any_allocation(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The grid size is checked from the numbers alone: the layout is never built and the
    request allocates next to nothing (traced by tracemalloc). Its speed is in
    docs/results/bounded-work.md (bench.bounded_work)."""
    # 1e-5 m over 4 x 4 m would be 1.6e11 grid points.
    body = small_room(
        room={"length": 4.0, "width": 4.0, "height": 3.0},
        grid={"step": 1e-5, "receiver_height": 0.8},
    )

    def refuse_to_build(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("the layout was built before its grid size was checked")

    monkeypatch.setattr(app.services.rooms, "layout_from_mapping", refuse_to_build)
    tracemalloc.start()
    try:
        response = client.post("/v1/rooms", json=body, headers=ADMIN)
        peak_bytes = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # The request needs well under 1 MB. One float64 per grid point would be 1.3 TB, a
    # chunk of a million of them 8 MB.
    assert peak_bytes < 4 * 1024**2, peak_bytes
    problem = assert_problem(response, 422, ["body.grid.step"])
    assert "1.6e+11" in problem["detail"]


def test_led_and_grid_limits_come_from_settings(tmp_path: Any) -> None:
    settings = make_settings(tmp_path, max_leds=1, max_grid_points=16)
    from app.main import create_app

    with TestClient(create_app(settings)) as limited:
        assert_problem(
            limited.post("/v1/rooms", json=small_room(), headers=ADMIN), 422, ["body.leds"]
        )
        one_led = small_room(leds=[{"x": 1.0, "y": 0.5}])
        # 2 x 1 m at 0.25 m is 32 points > 16.
        assert_problem(
            limited.post("/v1/rooms", json=one_led, headers=ADMIN), 422, ["body.grid.step"]
        )
        coarse = small_room(leds=[{"x": 1.0, "y": 0.5}], grid={"step": 0.5, "receiver_height": 0.8})
        assert limited.post("/v1/rooms", json=coarse, headers=ADMIN).status_code == 201


def test_led_normal_is_stored_normalised_and_bad_normals_name_the_field(
    client: TestClient,
) -> None:
    tilted = small_room(leds=[{"x": 1.0, "y": 0.5, "z": 2.0, "normal": [0.0, 0.5, -1.0]}])
    response = client.post("/v1/rooms", json=tilted, headers=ADMIN)
    assert response.status_code == 201, response.text
    normal = response.json()["layout"]["leds"][0]["normal"]
    assert normal == pytest.approx([0.0, 0.5 / 1.25**0.5, -1.0 / 1.25**0.5])
    for bad in ([0.0, 0.0, 1.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -1.0], None):
        body = small_room(leds=[{"x": 1.0, "y": 0.5, "z": 2.0, "normal": bad}])
        assert_problem(
            client.post("/v1/rooms", json=body, headers=ADMIN), 422, ["body.leds.0.normal"]
        )


def test_led_beam_is_stored_and_bad_beams_name_the_field(client: TestClient) -> None:
    beam = {"angles_deg": [0, 30, 60, 90], "relative_intensity": [10.0, 11.0, 6.0, 0.0]}
    body = small_room(leds=[{"x": 1.0, "y": 0.5, "z": 2.0, "beam": beam}])
    response = client.post("/v1/rooms", json=body, headers=ADMIN)
    assert response.status_code == 201, response.text
    assert response.json()["layout"]["leds"][0]["beam"] == {
        "angles_deg": [0.0, 30.0, 60.0, 90.0],
        "relative_intensity": [10.0, 11.0, 6.0, 0.0],
    }
    bad_beams = (
        ({"angles_deg": [5, 30], "relative_intensity": [1, 1]}, "angles_deg"),
        ({"angles_deg": [0, 30, 20], "relative_intensity": [1, 1, 1]}, "angles_deg"),
        ({"angles_deg": [0, 95], "relative_intensity": [1, 1]}, "angles_deg"),
        ({"angles_deg": [0, 30], "relative_intensity": [0, 1]}, "relative_intensity"),
        ({"angles_deg": [0, 30], "relative_intensity": [1, -1]}, "relative_intensity"),
        ({"angles_deg": [0, 30, 60], "relative_intensity": [1, 1]}, None),
    )
    for bad, name in bad_beams:
        body = small_room(leds=[{"x": 1.0, "y": 0.5, "z": 2.0, "beam": bad}])
        where = "body.leds.0.beam" + (f".{name}" if name else "")
        assert_problem(client.post("/v1/rooms", json=body, headers=ADMIN), 422, [where])
