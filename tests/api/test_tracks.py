"""Tracking through the HTTP API: `track`/`time` on measurements, the tracks resources, the
stream and its resumption, epochs, settings, and time on a stepped clock."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.clock import FakeClock
from app.main import create_app
from app.services.tracking import Tracking
from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, make_settings, wait_for_room

START = datetime(2026, 3, 1, 9, 0, tzinfo=UTC)
PAPER = paper_layout()
NOISE_STD = noise_std_for_snr(build_fingerprint(PAPER), 30.0)
# The one URL the view's files may name: SVG's namespace, an identifier never fetched.
SVG_NAMESPACE = "http://www.w3.org/2000/svg"


@pytest.fixture(scope="module")
def app_clock(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, FakeClock]]:
    """An app on a stepped clock (no sweeper thread: tests sweep when they step time)."""
    clock = FakeClock(START)
    settings = make_settings(
        tmp_path_factory.mktemp("tracks"), embedded_workers=1, epoch_sweep_seconds=0
    )
    with TestClient(create_app(settings, clock=clock)) as client:
        yield client, clock


@pytest.fixture
def room(app_clock: tuple[TestClient, FakeClock]) -> str:
    """A fresh paper room with a ready fingerprint (each test its own tracks)."""
    client, _ = app_clock
    body = {**PAPER.to_mapping(), "name": "walkers"}
    created = client.post("/v1/rooms", json=body, headers=ADMIN)
    assert created.status_code == 201, created.text
    wait_for_room(client, created.json()["id"])
    return str(created.json()["id"])


def _terminals(positions: list[tuple[float, float]], seed: int) -> list[dict[str, Any]]:
    amplitudes = noisy_amplitudes(PAPER, np.array(positions), NOISE_STD, rng=seed)
    return [{"id": f"t{k}", "amplitudes": row.tolist()} for k, row in enumerate(amplitudes)]


def _post(client: TestClient, room: str, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    answer: dict[str, Any] = response.json()
    return answer


def _at(seconds: float) -> str:
    return (START + timedelta(seconds=seconds)).isoformat()


def _events(
    client: TestClient, room: str, last_event_id: str | None, count: int
) -> list[dict[str, Any]]:
    """The first ``count`` events of the room's stream (``event``, ``id``, parsed ``data``)."""
    headers = dict(TERMINAL)
    if last_event_id is not None:
        headers["Last-Event-ID"] = last_event_id
    events: list[dict[str, Any]] = []
    current: dict[str, Any] = {}
    with client.stream("GET", f"/v1/rooms/{room}/tracks/stream", headers=headers) as stream:
        assert stream.status_code == 200
        assert stream.headers["content-type"].startswith("text/event-stream")
        for line in stream.iter_lines():
            if not line:
                if "data" in current:
                    events.append(current)
                current = {}
                if len(events) == count:
                    break
                continue
            name, _, value = line.partition(": ")
            if name in ("event", "id"):
                current[name] = value
            elif name == "data":
                current["data"] = json.loads(value)
    return events


def test_without_track_the_answer_and_the_room_stay_as_they_were(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    body = {"terminals": _terminals([(1.0, 1.0)], seed=1)}
    for extra in ({}, {"track": False}, {"track": False, "time": _at(0)}):
        answer = _post(client, room, {**body, **extra})
        assert set(answer["estimates"][0]) == {
            "x",
            "y",
            "grid_index",
            "weight",
            "terminal_id",
            "accuracy_m",
            "covariance",
            "gain",
            "z",
        }
    tracks = client.get(f"/v1/rooms/{room}/tracks", headers=TERMINAL).json()
    assert tracks == {"items": [], "next_cursor": None}


def test_terminals_update_their_own_tracks(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    ids: list[list[str]] = []
    for step in range(4):
        body = {
            "terminals": _terminals([(1.0 + 0.1 * step, 1.0), (3.0, 3.0)], seed=step),
            "track": True,
            "time": _at(0.2 * step),
        }
        answer = _post(client, room, body)
        ids.append([e["track_id"] for e in answer["estimates"]])
        tracked = answer["estimates"][0]["tracked"]
        assert tracked["time"] == _at(0.2 * step).replace("+00:00", "Z")
        assert tracked["accuracy_m"] > 0 and len(tracked["covariance"]) == 2
    assert all(row == ids[0] for row in ids) and len(set(ids[0])) == 2
    tracks = client.get(f"/v1/rooms/{room}/tracks", headers=TERMINAL).json()["items"]
    assert {t["terminal_id"] for t in tracks} == {"t0", "t1"}
    assert {t["status"] for t in tracks} == {"confirmed"}
    walker = next(t for t in tracks if t["terminal_id"] == "t0")
    assert walker["updates"] == 4 and walker["vx"] > 0.1  # it walks along x
    assert client.get(f"/v1/rooms/{room}/tracks/{walker['id']}", headers=TERMINAL).json() == walker
    points = client.get(f"/v1/rooms/{room}/tracks/{walker['id']}/points", headers=TERMINAL).json()
    assert len(points["items"]) == 4 and points["next_cursor"] is None
    assert points["items"][-1]["x"] == pytest.approx(walker["x"])
    since = client.get(
        f"/v1/rooms/{room}/tracks/{walker['id']}/points",
        params={"since": _at(0.3)},
        headers=TERMINAL,
    ).json()
    assert len(since["items"]) == 2


def test_a_measurement_older_than_its_track_is_history_only(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    first = _post(
        client, room, {"terminals": _terminals([(2.0, 2.0)], 1), "track": True, "time": _at(5)}
    )
    late = _post(
        client, room, {"terminals": _terminals([(3.0, 1.0)], 2), "track": True, "time": _at(4)}
    )
    assert late["estimates"][0]["tracked"] == first["estimates"][0]["tracked"]
    track_id = first["estimates"][0]["track_id"]
    points = client.get(f"/v1/rooms/{room}/tracks/{track_id}/points", headers=TERMINAL).json()
    assert [p["raw"]["x"] for p in points["items"]] == pytest.approx(
        [first["estimates"][0]["x"], late["estimates"][0]["x"]]
    )


def test_anonymous_estimates_keep_their_tracks(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    previous: list[tuple[str, float]] | None = None
    for step in range(3):
        amplitudes = noisy_amplitudes(
            PAPER, np.array([[1.0, 1.2], [2.9, 3.1 - 0.1 * step]]), NOISE_STD, rng=10 + step
        )
        body = {"correlation": (amplitudes.T @ amplitudes).tolist(), "targets": 2, "track": True}
        body["time"] = _at(0.2 * step)
        answer = _post(client, room, body)
        labels = sorted((e["track_id"], round(e["x"], 1)) for e in answer["estimates"])
        if previous is not None:
            assert [label for label, _ in labels] == [label for label, _ in previous]
        previous = labels
    statuses = [
        t["status"]
        for t in client.get(f"/v1/rooms/{room}/tracks", headers=TERMINAL).json()["items"]
    ]
    assert statuses == ["confirmed", "confirmed"]


def test_batch_items_track_in_their_order(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    items = [
        {"terminals": _terminals([(1.0 + 0.2 * k, 2.0)], k), "track": True, "time": _at(0.2 * k)}
        for k in range(3)
    ]
    items.append({"terminals": _terminals([(2.0, 2.0)], 9), "track": True, "time": "yesterday"})
    answer = client.post(
        f"/v1/rooms/{room}/localize/batch", json={"items": items}, headers=TERMINAL
    )
    assert answer.status_code == 200
    results = answer.json()["items"]
    assert len({r["estimates"][0]["track_id"] for r in results[:3]}) == 1
    times = [datetime.fromisoformat(r["estimates"][0]["tracked"]["time"]) for r in results[:3]]
    assert times == [START + timedelta(seconds=0.2 * k) for k in range(3)]
    assert results[3]["status"] == 422
    assert [e["field"] for e in results[3]["errors"]] == ["body.items.3.time"]


def test_bad_tracking_input_is_a_problem_naming_the_field(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    body = {"terminals": _terminals([(1.0, 1.0)], 1)}
    url = f"/v1/rooms/{room}/localize"
    for bad, field in (
        ({"track": "yes"}, "body.track"),
        ({"track": True, "time": "2026-03-01T09:00:00"}, "body.time"),  # no offset
        ({"track": True, "time": _at(3600)}, "body.time"),  # far ahead of the clock
    ):
        assert_problem(client.post(url, json={**body, **bad}, headers=TERMINAL), 422, [field])
    stream = client.get(
        f"/v1/rooms/{room}/tracks/stream", headers={**TERMINAL, "Last-Event-ID": "abc"}
    )
    assert_problem(stream, 422, ["header.Last-Event-ID"])
    assert_problem(client.get("/v1/rooms/nope/tracks/stream", headers=TERMINAL), 404)
    assert_problem(client.get(f"/v1/rooms/{room}/tracks/nope", headers=TERMINAL), 404)
    assert_problem(
        client.get(f"/v1/rooms/{room}/tracks", params={"status": "gone"}, headers=TERMINAL), 422
    )
    unknown = "0" * 32
    assert_problem(client.delete(f"/v1/rooms/{room}/tracks/{unknown}", headers=TERMINAL), 403)
    assert_problem(client.delete(f"/v1/rooms/{room}/tracks/{unknown}", headers=ADMIN), 404)
    assert_problem(client.get(f"/v1/rooms/{room}/tracks/{unknown}/points", headers=TERMINAL), 404)


def test_the_stream_resumes_after_last_event_id_losing_nothing(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    for step in range(4):
        body = {
            "terminals": _terminals([(1.0, 1.0 + 0.1 * step)], step),
            "track": True,
            "time": _at(0.2 * step),
        }
        _post(client, room, body)
    every = _events(client, room, "0", 4)
    assert [e["id"] for e in every] == ["1", "2", "3", "4"]
    assert {e["event"] for e in every} == {"track"}
    resumed = _events(client, room, "2", 2)
    assert resumed == every[2:]
    # Without Last-Event-ID: the current tracks first, then what follows.
    opening = _events(client, room, None, 1)
    assert opening[0]["id"] == "4" and opening[0]["data"]["updates"] == 4


def test_tracks_are_lost_then_removed_as_time_passes(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, clock = app_clock
    tracking: Tracking = client.app.state.tracking  # type: ignore[attr-defined]
    now = clock.now()
    answer = _post(
        client,
        room,
        {"terminals": _terminals([(2.0, 2.0)], 3), "track": True, "time": now.isoformat()},
    )
    track_id = answer["estimates"][0]["track_id"]
    settings = client.get(f"/v1/rooms/{room}/tracking", headers=TERMINAL).json()
    last = int(client.get(f"/v1/rooms/{room}/tracks/{track_id}", headers=TERMINAL).status_code)
    assert last == 200
    clock.advance(settings["lost_after_s"] + 0.1)
    assert tracking.sweep() >= 1
    assert client.get(f"/v1/rooms/{room}/tracks", headers=TERMINAL).json()["items"] == []
    lost = client.get(f"/v1/rooms/{room}/tracks", params={"status": "lost"}, headers=TERMINAL)
    assert [t["id"] for t in lost.json()["items"]] == [track_id]
    clock.advance(settings["drop_after_s"])
    tracking.sweep()
    assert_problem(client.get(f"/v1/rooms/{room}/tracks/{track_id}", headers=TERMINAL), 404)
    kinds = [(e["event"], e["data"]["id"]) for e in _events(client, room, "0", 3)]
    assert kinds == [("track", track_id), ("track", track_id), ("removed", track_id)]


def test_history_is_pruned_at_most_every_tenth_of_history_s(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    """Points older than `history_s` go with the first update a tenth of `history_s` after
    the last one that pruned: kept for `history_s`, never more than a tenth longer."""
    client, clock = app_clock
    settings = {"history_s": 10.0, "lost_after_s": 30.0, "drop_after_s": 60.0}
    assert client.put(f"/v1/rooms/{room}/tracking", json=settings, headers=ADMIN).status_code == 200
    start = clock.now()
    body = {"terminals": _terminals([(2.0, 2.0)], 3), "track": True}  # measured now

    def post_at(offset_s: float) -> str:
        clock.advance(offset_s - (clock.now() - start).total_seconds())
        return str(_post(client, room, body)["estimates"][0]["track_id"])

    def kept(track_id: str) -> list[float]:
        url = f"/v1/rooms/{room}/tracks/{track_id}/points"
        items = client.get(url, headers=TERMINAL).json()["items"]
        return [
            round((datetime.fromisoformat(p["time"]) - start).total_seconds(), 3) for p in items
        ]

    track_id = post_at(0.0)
    post_at(0.5)
    assert kept(track_id) == [0.0, 0.5]
    post_at(10.3)  # prunes what is older than 0.3
    assert kept(track_id) == [0.5, 10.3]
    post_at(10.9)  # 0.6 s after the last pruning: 0.5 is kept, 0.4 s past history_s
    assert kept(track_id) == [0.5, 10.3, 10.9]
    post_at(11.4)  # 1.1 s after: prunes what is older than 1.4
    assert kept(track_id) == [10.3, 10.9, 11.4]


def test_an_admin_ends_a_track_and_the_terminal_starts_a_new_one(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, clock = app_clock
    body = {"terminals": _terminals([(2.0, 2.0)], 3), "track": True}
    first = _post(client, room, {**body, "time": clock.now().isoformat()})["estimates"][0][
        "track_id"
    ]
    assert client.delete(f"/v1/rooms/{room}/tracks/{first}", headers=ADMIN).status_code == 204
    second = _post(client, room, {**body, "time": clock.now().isoformat()})["estimates"][0][
        "track_id"
    ]
    assert second != first


def test_epochs_track_by_default(app_clock: tuple[TestClient, FakeClock], room: str) -> None:
    client, _ = app_clock
    for track, expect in ((None, True), (False, False)):
        create = {} if track is None else {"track": track}
        epoch = client.post(f"/v1/rooms/{room}/epochs", json=create, headers=TERMINAL).json()
        assert epoch["track"] is expect
        for terminal in _terminals([(1.0, 1.0), (3.0, 2.5)], 4):
            post = {"terminal_id": terminal["id"], "amplitudes": terminal["amplitudes"]}
            response = client.post(
                f"/v1/rooms/{room}/epochs/{epoch['id']}/measurements", json=post, headers=TERMINAL
            )
            assert response.status_code == 202, response.text
        solved = client.post(
            f"/v1/rooms/{room}/epochs/{epoch['id']}/solve", headers=TERMINAL
        ).json()
        assert solved["status"] == "solved"
        estimates = solved["localization"]["estimates"]
        assert all(("track_id" in e) is expect for e in estimates)
    tracks = client.get(f"/v1/rooms/{room}/tracks", headers=TERMINAL).json()["items"]
    assert sorted(t["terminal_id"] for t in tracks) == ["t0", "t1"]


def test_tracking_settings_change_without_a_rebuild(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    url = f"/v1/rooms/{room}/tracking"
    defaults = client.get(url, headers=TERMINAL).json()
    assert_problem(client.put(url, json={"lost_after_s": 2.0}, headers=TERMINAL), 403)
    changed = client.put(url, json={"lost_after_s": 2.0, "max_speed_mps": 2.0}, headers=ADMIN)
    assert changed.status_code == 200
    assert changed.json() == {**defaults, "lost_after_s": 2.0, "max_speed_mps": 2.0}
    restored = client.put(url, json={"lost_after_s": None}, headers=ADMIN).json()
    assert restored == {**defaults, "max_speed_mps": 2.0}
    assert_problem(
        client.put(url, json={"lost_after_s": 100.0, "drop_after_s": 10.0}, headers=ADMIN),
        422,
        ["body.drop_after_s"],
    )
    assert_problem(client.put(url, json={"history_s": -1}, headers=ADMIN), 422, ["body.history_s"])
    room_state = client.get(f"/v1/rooms/{room}", headers=TERMINAL).json()
    assert (
        room_state["fingerprint"]["version"] == 1 and room_state["fingerprint"]["status"] == "ready"
    )


def test_the_accuracy_map_covers_the_room(
    app_clock: tuple[TestClient, FakeClock], room: str
) -> None:
    client, _ = app_clock
    accuracy = client.get(f"/v1/rooms/{room}/tracking/accuracy", headers=TERMINAL).json()
    assert accuracy["x_edges"][0] == 0.0 and accuracy["x_edges"][-1] == pytest.approx(4.0)
    assert len(accuracy["accuracy_m"]) == len(accuracy["y_edges"]) - 1
    values = [v for row in accuracy["accuracy_m"] for v in row if v is not None]
    assert values and 0 < min(values) < 0.05


def test_the_view_is_served_from_the_package_with_a_strict_policy(tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(tmp_path))) as client:
        page = client.get("/view")
        assert page.status_code == 200
        assert page.headers["content-security-policy"] == "default-src 'self'"
        for name in ("view.js", "view.css", "favicon.svg"):
            asset = client.get(f"/view/{name}")
            assert asset.status_code == 200, name
            assert asset.headers["content-security-policy"] == "default-src 'self'"
            assert "http" not in asset.text.replace(SVG_NAMESPACE, ""), name
        assert "http" not in page.text.replace(SVG_NAMESPACE, "")
        assert_problem(client.get("/view/secrets.txt"), 404)
