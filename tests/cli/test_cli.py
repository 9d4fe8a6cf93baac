"""The ``vlp`` command, run as ``main([...])`` against a live ``vlp serve``."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.cli import EXIT_NO_ANSWER, EXIT_REFUSED, EXIT_USAGE, main
from app.cli import _remote as remote_commands
from app.client import VLPClient
from app.schemas.localize import localize_example
from tests.live_server import ADMIN_KEY, TERMINAL_KEY, LiveServer, live_server

REPO = Path(__file__).resolve().parents[2]
PAPER_ROOM = REPO / "examples" / "paper-room.json"
_KEY_VARIABLES = ("VLP_API_KEY", "VLP_ADMIN_KEYS", "VLP_TERMINAL_KEYS", "VLP_URL")


@pytest.fixture(autouse=True)
def _no_ambient_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    """The commands must not pick up a key or URL from the developer's shell."""
    for variable in _KEY_VARIABLES:
        monkeypatch.delenv(variable, raising=False)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveServer, str]]:
    """A live server with the demo room ready; yields it and the room id."""
    with live_server(tmp_path_factory.mktemp("cli"), VLP_DEMO="1") as live:
        with VLPClient(live.url, api_key=TERMINAL_KEY) as client:
            room_id = client.list_rooms().items[0].id
            client.wait_for_room(room_id, timeout_s=90)
        yield live, room_id


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _json(
    capsys: pytest.CaptureFixture[str], server: LiveServer, *argv: str, key: str = ADMIN_KEY
) -> Any:
    code, out, err = _run(capsys, *argv, "--json", "--url", server.url, "--key", key)
    assert code == 0, err
    return json.loads(out)


@pytest.mark.slow
def test_rooms_list_and_status(
    server: tuple[LiveServer, str], capsys: pytest.CaptureFixture[str]
) -> None:
    live, room_id = server
    rooms = _json(capsys, live, "rooms", "list", key=TERMINAL_KEY)
    assert [(room["id"], room["name"]) for room in rooms][:1] == [(room_id, "Paper room")]
    status = _json(capsys, live, "rooms", "status", room_id)
    assert status["room"]["fingerprint"]["status"] == "ready"
    assert status["job"]["status"] == "succeeded"
    code, out, _ = _run(capsys, "rooms", "list", "--url", live.url, "--key", TERMINAL_KEY)
    assert code == 0 and room_id in out and "Paper room" in out


@pytest.mark.slow
def test_rooms_create_waits_then_rebuild_shows_progress(
    server: tuple[LiveServer, str], capsys: pytest.CaptureFixture[str]
) -> None:
    live, _ = server
    room = _json(capsys, live, "rooms", "create", str(PAPER_ROOM))
    assert room["name"] == "Meeting room 2.14"
    assert room["fingerprint"]["status"] == "ready" and room["fingerprint"]["version"] == 1
    code, out, err = _run(capsys, "rooms", "rebuild", room["id"], "--url", live.url)
    assert code == 1 and "401" in err  # no key anywhere: refused, not crashed
    code, out, err = _run(
        capsys, "rooms", "rebuild", room["id"], "--url", live.url, "--key", ADMIN_KEY
    )
    assert code == 0, err
    assert json.loads(out)["result"]["fingerprint_version"] == 2
    assert "100%" in err and "succeeded" in err  # the progress bar, on stderr
    assert _json(capsys, live, "rooms", "delete", room["id"]) == {"deleted": room["id"]}


@pytest.mark.slow
def test_simulate_and_localize(
    server: tuple[LiveServer, str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    live, room_id = server
    result = _json(capsys, live, "simulate", room_id, "--targets", "3", "--seed", "5", "--localize")
    assert len(result["truth"]) == 3 and len(result["localization"]["estimates"]) == 3
    measurement = tmp_path / "measurement.json"
    measurement.write_text(json.dumps(localize_example()), encoding="utf-8")
    located = _json(capsys, live, "localize", room_id, str(measurement), key=TERMINAL_KEY)
    assert located["targets"] == 3 and located["room_id"] == room_id
    code, out, err = _run(
        capsys, "simulate", room_id, "--localize", "--url", live.url, "--key", TERMINAL_KEY
    )
    assert code == 0, err
    assert "8 estimates (gridless" in out and "to nearest truth" in out


@pytest.mark.slow
def test_localize_batch(
    server: tuple[LiveServer, str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    live, room_id = server
    batch = tmp_path / "batch.json"
    batch.write_text(json.dumps({"items": [localize_example()] * 2}), encoding="utf-8")
    answers = _json(capsys, live, "localize", room_id, str(batch), "--batch", key=TERMINAL_KEY)
    assert [answer["targets"] for answer in answers] == [3, 3]
    batch.write_text(json.dumps([localize_example(), {"targets": 1}]), encoding="utf-8")
    code, out, err = _run(
        capsys, "localize", room_id, str(batch), "--batch", "--url", live.url, "--key", ADMIN_KEY
    )
    assert code == 1, err
    assert "2 answers" in out and "422" in out


@pytest.mark.slow
def test_errors_exit_with_the_problem(
    server: tuple[LiveServer, str], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    live, _ = server
    code, out, err = _run(
        capsys, "rooms", "show", "nope", "--json", "--url", live.url, "--key", ADMIN_KEY
    )
    assert code == EXIT_REFUSED
    assert json.loads(out)["status"] == 404 and "no room with id 'nope'" in err
    layout = json.loads(PAPER_ROOM.read_text(encoding="utf-8"))
    layout["leds"][0]["z"] = 5.0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(layout), encoding="utf-8")
    code, out, err = _run(
        capsys, "rooms", "create", str(bad), "--json", "--url", live.url, "--key", ADMIN_KEY
    )
    assert code == EXIT_REFUSED
    assert [e["field"] for e in json.loads(out)["errors"]] == ["body.leds.0.z"]
    assert "body.leds.0.z" in err
    broken = tmp_path / "broken.json"
    broken.write_text("{not json", encoding="utf-8")
    code, out, err = _run(capsys, "rooms", "create", str(broken), "--url", live.url)
    assert code == EXIT_USAGE and out == "" and f"cannot read {broken}" in err


def test_unreachable_service_exits_3(capsys: pytest.CaptureFixture[str]) -> None:
    # A port this test holds bound but never listens on: connections to it are refused, and
    # no other process can start listening there while the test runs.
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{closed.getsockname()[1]}"
        code, out, err = _run(capsys, "rooms", "list", "--url", url, "--key", "k")
    assert code == EXIT_NO_ANSWER and out == "" and f"no answer from {url}" in err


@pytest.mark.slow
def test_calibrate_posts_the_survey_and_prints_the_report(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The calibration endpoints live on another branch: a fake service stands in."""
    survey = {"survey": [{"x": 1.0, "y": 1.0, "led": 0, "amplitude": 2e-5}], "masked_leds": [2]}
    job = {"id": "j1", "kind": "calibrate", "status": "queued", "progress": 0.0}
    seen: list[Any] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append((request.method, request.url.path))
        if request.method == "POST":
            assert json.loads(request.content) == survey
            return httpx.Response(202, json=job, headers={"Location": "/v1/jobs/j1"})
        if request.url.path == "/v1/jobs/j1":
            done = {**job, "status": "succeeded", "progress": 1.0}
            return httpx.Response(200, json={**done, "result": {"calibration_id": "c9"}})
        return httpx.Response(200, json={"id": "c9", "leds": 16})

    def fake_client(_args: Any) -> VLPClient:
        return VLPClient("http://vlp.test", transport=httpx.MockTransport(handler))

    monkeypatch.setattr(remote_commands, "open_client", fake_client)
    path = tmp_path / "survey.json"
    path.write_text(json.dumps(survey), encoding="utf-8")
    code, out, err = _run(capsys, "rooms", "calibrate", "r1", str(path), "--json")
    assert code == 0, err
    assert json.loads(out) == {"id": "c9", "leds": 16}
    assert seen == [
        ("POST", "/v1/rooms/r1/calibrations"),
        ("GET", "/v1/jobs/j1"),
        ("GET", "/v1/rooms/r1/calibrations/c9"),
    ]


def test_demo_walkers_post_tracked_walkers_then_stop(
    capsys: pytest.CaptureFixture[str], server: tuple[LiveServer, str]
) -> None:
    live, room_id = server
    args = ["demo", "walkers", "--count", "3", "--steps", "5", "--rate-hz", "50", "--seed", "2"]
    answer = _json(capsys, live, *args, key=TERMINAL_KEY)
    assert answer == {"room_id": room_id, "steps": 5, "walkers": 3}
    with VLPClient(live.url, api_key=TERMINAL_KEY) as client:
        tracks = client.list_tracks(room_id).items
    walkers = {
        t.terminal_id: t for t in tracks if t.terminal_id and t.terminal_id.startswith("walker-")
    }
    assert sorted(walkers) == ["walker-1", "walker-2", "walker-3"]
    assert all(t.updates == 5 and t.status == "confirmed" for t in walkers.values())
    code, _, err = _run(capsys, *args, "--room", "nope", "--url", live.url, "--key", TERMINAL_KEY)
    assert code == EXIT_REFUSED and "nope" in err
