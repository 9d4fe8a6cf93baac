"""Pictures over HTTP: map.png (cached per fingerprint version and options) and
localization.png."""

from __future__ import annotations

import io

import pytest
from PIL import Image

from app.schemas.rooms import paper_room_example
from app.services.picture_cache import PictureCache

from .conftest import (
    ADMIN,
    TERMINAL,
    TestClient,
    assert_problem,
    small_room,
    wait_for_job,
    wait_for_room,
)


def _png(content: bytes) -> Image.Image:
    image = Image.open(io.BytesIO(content))
    image.load()  # decodes every pixel: a truncated or corrupt file raises here
    return image


def _pictures(client: TestClient) -> PictureCache:
    cache: PictureCache = client.app.state.pictures  # type: ignore[attr-defined]
    return cache


def test_map_png_is_a_png_and_cached(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    url = f"/v1/rooms/{room_id}/map.png?width_px=640"
    first = client.get(url, headers=TERMINAL)
    assert first.status_code == 200, first.text
    assert first.headers["content-type"] == "image/png"
    image = _png(first.content)
    assert image.format == "PNG" and image.size[0] == 640 and image.size[1] > 300
    hits = _pictures(client).hits
    second = client.get(url, headers=TERMINAL)
    assert second.content == first.content
    assert _pictures(client).hits == hits + 1
    assert second.headers["etag"] == first.headers["etag"]
    assert second.headers["x-fingerprint-version"] == "1"
    again = client.get(url, headers={**TERMINAL, "If-None-Match": first.headers["etag"]})
    assert again.status_code == 304 and again.content == b""


@pytest.mark.parametrize("heatmap", ["crlb", "none"])
def test_map_png_other_heatmaps_differ(ready_app: tuple[TestClient, str], heatmap: str) -> None:
    client, room_id = ready_app
    url = f"/v1/rooms/{room_id}/map.png?width_px=400"
    coverage = client.get(f"{url}&heatmap=coverage", headers=ADMIN)
    other = client.get(f"{url}&heatmap={heatmap}", headers=ADMIN)
    assert other.status_code == 200
    assert _png(other.content).size[0] == 400
    assert other.content != coverage.content


def test_default_map_of_the_demo_room_is_not_one_flat_colour(
    ready_app: tuple[TestClient, str],
) -> None:
    """Every point of the paper's room sees all 16 LEDs, so coverage is one colour; the
    default (`auto`) then draws the CRLB, which varies over the room."""
    client, room_id = ready_app
    url = f"/v1/rooms/{room_id}/map.png?width_px=400"
    default = client.get(url, headers=ADMIN).content
    assert default == client.get(f"{url}&heatmap=crlb", headers=ADMIN).content
    assert default != client.get(f"{url}&heatmap=coverage", headers=ADMIN).content

    def commonest_colour_share(content: bytes) -> float:
        # Inside the room, away from the colour bar and labels.
        image = _png(content).convert("RGB")
        width, height = image.size
        box = image.crop((width // 4, height // 3, width // 2, 2 * height // 3))
        colours = box.getcolors(maxcolors=box.width * box.height)
        assert colours is not None
        return max(count for count, _ in colours) / (box.width * box.height)

    coverage = client.get(f"{url}&heatmap=coverage", headers=ADMIN).content
    assert commonest_colour_share(coverage) > 0.5  # flat: every point sees all 16 LEDs
    assert commonest_colour_share(default) < 0.2


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("heatmap=heat", "query.heatmap"),
        ("width_px=50", "query.width_px"),
        ("snr_db=nan", "query.snr_db"),
        ("fingerprint_version=0", "query.fingerprint_version"),
    ],
    ids=["heatmap", "width", "snr", "version"],
)
def test_map_png_bad_options_are_422(
    ready_app: tuple[TestClient, str], query: str, field: str
) -> None:
    client, room_id = ready_app
    response = client.get(f"/v1/rooms/{room_id}/map.png?{query}", headers=TERMINAL)
    assert_problem(response, 422, [field])


def test_map_png_needs_a_key_and_a_known_room_and_version(
    ready_app: tuple[TestClient, str],
) -> None:
    client, room_id = ready_app
    assert_problem(client.get(f"/v1/rooms/{room_id}/map.png"), 401)
    assert_problem(client.get("/v1/rooms/nope/map.png", headers=TERMINAL), 404)
    missing = client.get(f"/v1/rooms/{room_id}/map.png?fingerprint_version=99", headers=TERMINAL)
    assert_problem(missing, 404)


def test_map_png_of_a_room_without_fingerprint_draws_its_layout(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    response = client.get(f"/v1/rooms/{room['id']}/map.png", headers=TERMINAL)
    assert response.status_code == 200
    assert "x-fingerprint-version" not in response.headers
    assert _png(response.content).format == "PNG"


def test_new_fingerprint_version_changes_the_cache_key(worker_app: TestClient) -> None:
    client = worker_app
    room_id = client.post("/v1/rooms", json=paper_room_example(), headers=ADMIN).json()["id"]
    wait_for_room(client, room_id)
    url = f"/v1/rooms/{room_id}/map.png?width_px=300"
    first = client.get(url, headers=TERMINAL)
    assert first.headers["x-fingerprint-version"] == "1"
    entries, misses = len(_pictures(client)), _pictures(client).misses
    # A masking calibration makes version 2 (15 LEDs drawn): a new key, a new picture.
    job = client.post(
        f"/v1/rooms/{room_id}/calibrations", json={"masked_leds": [0]}, headers=ADMIN
    ).json()
    assert wait_for_job(client, job["id"])["result"]["fingerprint_version"] == 2
    second = client.get(url, headers=TERMINAL)
    assert second.headers["x-fingerprint-version"] == "2"
    assert _pictures(client).misses == misses + 1 and len(_pictures(client)) == entries + 1
    assert second.content != first.content
    pinned = client.get(f"{url}&fingerprint_version=1", headers=TERMINAL)
    assert pinned.content == first.content
    assert "immutable" in pinned.headers["cache-control"]


def test_localization_png_draws_estimates_and_truth(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    simulation = client.post(
        f"/v1/rooms/{room_id}/simulate",
        json={"targets": 3, "seed": 2, "form": "terminals"},
        headers=TERMINAL,
    ).json()
    localization = client.post(
        f"/v1/rooms/{room_id}/localize", json=simulation["measurement"], headers=TERMINAL
    ).json()
    body = {
        "estimates": localization["estimates"],
        "truth": simulation["truth"],
        "width_px": 500,
    }
    response = client.post(f"/v1/rooms/{room_id}/localization.png", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    assert _png(response.content).size[0] == 500
    without_truth = client.post(
        f"/v1/rooms/{room_id}/localization.png",
        json={"estimates": localization["estimates"], "width_px": 500},
        headers=TERMINAL,
    )
    assert without_truth.status_code == 200
    assert without_truth.content != response.content


def test_localization_png_bad_bodies_are_422(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    url = f"/v1/rooms/{room_id}/localization.png"
    assert_problem(
        client.post(url, json={"estimates": [{"y": 1.0}]}, headers=TERMINAL),
        422,
        ["body.estimates.0.x"],
    )
    assert_problem(
        client.post(url, json={"estimates": [], "width_px": 10}, headers=TERMINAL),
        422,
        ["body.width_px"],
    )
    assert_problem(client.post(url, json={"estimates": []}), 401)
