"""Epochs over HTTP: join, replace, solve once, expire, 409, labels, restart, two processes.

Every app runs on a :class:`FakeClock`: a window closes (and a solve claim runs out) when the
test advances the clock, so three posts always fit in a window however slow the machine is.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI

import app.services.epoch_settler
from app.clock import FakeClock
from app.main import create_app
from app.registry import Registry
from app.schemas.epochs import epoch_create_examples, epoch_measurement_examples
from app.vlp.errors import SolverError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, true_amplitudes
from tests.db_fixtures import build_now
from tests.waiting import wait_for

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, make_settings

TRUTH = np.array([[0.7, 0.9], [2.1, 3.3], [3.4, 1.5]])


def service(client: TestClient) -> FastAPI:
    assert isinstance(client.app, FastAPI)
    return client.app


def registry_of(client: TestClient) -> Registry:
    registry: Registry = service(client).state.registry
    return registry


def clock_of(client: TestClient) -> FakeClock:
    clock = service(client).state.clock
    assert isinstance(clock, FakeClock)
    return clock


def start(
    data_dir: Path, database_url: str, clock: FakeClock | None = None, **overrides: Any
) -> TestClient:
    """An app on ``database_url`` whose demo (paper) room has a ready fingerprint.

    It runs on ``clock`` (a new FakeClock when None); apps that stand for processes sharing
    one registry share one clock, as processes on one machine share its time.
    """
    values: dict[str, Any] = {"database_url": database_url, "demo": True}
    values["epoch_sweep_seconds"] = 0  # windows close lazily unless a test turns it on
    settings = make_settings(data_dir, **{**values, **overrides})
    client = TestClient(create_app(settings, clock=FakeClock() if clock is None else clock))
    client.__enter__()
    registry = registry_of(client)
    room_id = room_of(client)
    if registry.current_version(room_id=room_id) is None:
        build_now(registry, room_id=room_id)
    return client


def room_of(client: TestClient) -> str:
    rooms = client.get("/v1/rooms", headers=ADMIN).json()["items"]
    assert len(rooms) == 1
    return str(rooms[0]["id"])


@pytest.fixture
def client(tmp_path: Path, database_url: str) -> Iterator[TestClient]:
    test_client = start(tmp_path / "data", database_url)
    try:
        yield test_client
    finally:
        test_client.__exit__(None, None, None)


def create(client: TestClient, room_id: str, **body: Any) -> dict[str, Any]:
    response = client.post(f"/v1/rooms/{room_id}/epochs", json=body, headers=TERMINAL)
    assert response.status_code == 201, response.text
    epoch: dict[str, Any] = response.json()
    assert response.headers["location"] == f"/v1/rooms/{room_id}/epochs/{epoch['id']}"
    return epoch


def post(client: TestClient, epoch: dict[str, Any], terminal: str, amplitudes: Any) -> Any:
    return client.post(
        f"/v1/rooms/{epoch['room_id']}/epochs/{epoch['id']}/measurements",
        json={"terminal_id": terminal, "amplitudes": [float(a) for a in amplitudes]},
        headers=TERMINAL,
    )


def solve(client: TestClient, epoch: dict[str, Any]) -> dict[str, Any]:
    response = client.post(
        f"/v1/rooms/{epoch['room_id']}/epochs/{epoch['id']}/solve", headers=TERMINAL
    )
    assert response.status_code == 200, response.text
    result: dict[str, Any] = response.json()
    return result


def read(client: TestClient, epoch: dict[str, Any]) -> dict[str, Any]:
    response = client.get(f"/v1/rooms/{epoch['room_id']}/epochs/{epoch['id']}", headers=TERMINAL)
    assert response.status_code == 200, response.text
    result: dict[str, Any] = response.json()
    return result


def let_window_pass(client: TestClient, epoch: dict[str, Any]) -> None:
    """Advance the app's clock to the epoch's deadline: from then on its window is closed."""
    clock = clock_of(client)
    deadline = datetime.fromisoformat(epoch["expires_at"])
    clock.advance(max(0.0, (deadline - clock.now()).total_seconds()))


@functools.cache
def noise_std_30db() -> float:
    return noise_std_for_snr(build_fingerprint(paper_layout()), 30.0)


def terminal_amplitudes(seed: int) -> np.ndarray[Any, Any]:
    """What terminals at TRUTH measure at 30 dB SNR (the API's simulate convention)."""
    return noisy_amplitudes(paper_layout(), TRUTH, noise_std_30db(), rng=seed)


def assert_labelled_near_truth(epoch: dict[str, Any], names: list[str]) -> None:
    """Every estimate is labelled, each terminal once, with the terminal whose true position
    is nearest and within 0.25 m."""
    localization = epoch["localization"]
    assert localization["targets"] == len(names)
    truth = dict(zip(names, TRUTH.tolist(), strict=True))
    labels = [estimate["terminal_id"] for estimate in localization["estimates"]]
    assert sorted(labels) == sorted(names)
    for estimate in localization["estimates"]:
        distances = {
            name: math.hypot(estimate["x"] - x, estimate["y"] - y) for name, (x, y) in truth.items()
        }
        assert min(distances, key=distances.__getitem__) == estimate["terminal_id"], distances
        assert distances[estimate["terminal_id"]] < 0.25, (estimate, distances)


def test_terminals_join_replace_and_each_estimate_is_labelled(client: TestClient) -> None:
    room_id = room_of(client)
    epoch = create(client, room_id, window_s=60)
    assert epoch["status"] == "open" and epoch["terminals"] == 0
    assert epoch["min_terminals"] == 2 and epoch["model"] == "correlation"
    amplitudes = terminal_amplitudes(seed=3)
    # t2 first posts what it would measure at t1's spot, then corrects itself.
    assert post(client, epoch, "t2", amplitudes[0]).status_code == 202
    for name, row in zip(["t1", "t2", "t3"], amplitudes, strict=True):
        response = post(client, epoch, name, row)
        assert response.status_code == 202, response.text
    assert response.json()["terminals"] == 3
    solved = solve(client, epoch)
    assert solved["status"] == "solved" and solved["terminals"] == 3 and solved["error"] is None
    assert solved["localization"]["fingerprint_version"] == solved["fingerprint_version"] == 1
    assert_labelled_near_truth(solved, ["t1", "t2", "t3"])
    assert read(client, epoch) == solved


def test_labels_follow_the_terminals_not_their_posting_order(client: TestClient) -> None:
    epoch = create(client, room_of(client), model="power", solver="nnls")
    amplitudes = true_amplitudes(paper_layout(), TRUTH)
    names = ["c", "a", "b"]
    for index in (2, 0, 1):
        assert post(client, epoch, names[index], amplitudes[index]).status_code == 202
    solved = solve(client, epoch)
    assert solved["localization"]["model"] == "power"
    assert solved["localization"]["solver"] == "nnls"
    assert_labelled_near_truth(solved, names)


def test_a_closed_epoch_refuses_posts_and_stays_as_it_was(client: TestClient) -> None:
    epoch = create(client, room_of(client))
    amplitudes = terminal_amplitudes(seed=5)
    for name, row in zip(["t1", "t2", "t3"], amplitudes, strict=True):
        post(client, epoch, name, row)
    solved = solve(client, epoch)
    late = post(client, epoch, "t4", amplitudes[0])
    problem = assert_problem(late, 409)
    assert "solved" in problem["detail"]
    assert_problem(post(client, epoch, "t1", amplitudes[0]), 409)
    assert solve(client, epoch) == solved == read(client, epoch)


def test_too_few_terminals_expire_when_the_window_passes(client: TestClient) -> None:
    epoch = create(client, room_of(client), window_s=1.0, min_terminals=2)
    post(client, epoch, "t1", terminal_amplitudes(seed=1)[0])
    let_window_pass(client, epoch)
    assert_problem(post(client, epoch, "t2", terminal_amplitudes(seed=1)[1]), 409)
    expired = read(client, epoch)
    assert expired["status"] == "expired" and expired["localization"] is None
    assert expired["terminals"] == 1


def test_solve_with_too_few_terminals_expires_the_epoch(client: TestClient) -> None:
    epoch = create(client, room_of(client), min_terminals=3)
    for name, row in zip(["t1", "t2"], terminal_amplitudes(seed=2)[:2], strict=True):
        post(client, epoch, name, row)
    assert solve(client, epoch)["status"] == "expired"


def test_a_passed_window_is_solved_by_the_next_read(client: TestClient) -> None:
    epoch = create(client, room_of(client), window_s=1.0)
    for name, row in zip(["t1", "t2", "t3"], terminal_amplitudes(seed=4), strict=True):
        assert post(client, epoch, name, row).status_code == 202
    assert read(client, epoch)["status"] == "open"  # a read before the deadline leaves it open
    let_window_pass(client, epoch)
    solved = read(client, epoch)
    assert solved["status"] == "solved"
    assert_labelled_near_truth(solved, ["t1", "t2", "t3"])


@pytest.mark.parametrize(
    "body, field",
    [
        ({"min_terminals": 0}, "body.min_terminals"),
        ({"window_s": 0}, "body.window_s"),
        ({"window_s": 61}, "body.window_s"),
        ({"targets": 0}, "body.targets"),
        ({"solver": "magic"}, "body.solver"),
        ({"model": "mean"}, "body.model"),
        ({"windows": 2}, "body.windows"),
    ],
    ids=["min0", "window0", "window61", "targets0", "solver", "model", "unknown"],
)
def test_create_validation_names_the_field(
    client: TestClient, body: dict[str, Any], field: str
) -> None:
    response = client.post(f"/v1/rooms/{room_of(client)}/epochs", json=body, headers=TERMINAL)
    assert_problem(response, 422, [field])


@pytest.mark.parametrize(
    "body, field",
    [
        ({"terminal_id": "t1", "amplitudes": [1.0] * 15}, "body.amplitudes"),
        ({"terminal_id": "t1", "amplitudes": []}, "body.amplitudes"),
        ({"terminal_id": "t 1", "amplitudes": [1.0] * 16}, "body.terminal_id"),
        ({"amplitudes": [1.0] * 16}, "body.terminal_id"),
        ({"terminal_id": "t1", "amplitudes": [None] * 16}, "body.amplitudes"),
        (
            {"terminal_id": "t1", "amplitudes": [1.0] * 16, "detection_floor": -1.0},
            "body.detection_floor",
        ),
        (
            {"terminal_id": "t1", "amplitudes": [1.0] * 16, "detection_floor": 0.0},
            "body.detection_floor",
        ),
    ],
    ids=["short", "empty", "bad-id", "no-id", "nothing-detected", "floor-negative", "floor-zero"],
)
def test_post_validation_names_the_field(
    client: TestClient, body: dict[str, Any], field: str
) -> None:
    epoch = create(client, room_of(client))
    url = f"/v1/rooms/{epoch['room_id']}/epochs/{epoch['id']}/measurements"
    assert_problem(client.post(url, json=body, headers=TERMINAL), 422, [field])
    infinite = '{"terminal_id": "t1", "amplitudes": [1e999' + ", 1.0" * 15 + "]}"
    response = client.post(
        url, content=infinite, headers={**TERMINAL, "Content-Type": "application/json"}
    )
    assert_problem(response, 422, ["body.amplitudes.0"])
    assert read(client, epoch)["terminals"] == 0


def test_unknown_room_or_epoch_is_404_and_keys_are_needed(client: TestClient) -> None:
    room_id = room_of(client)
    epoch = create(client, room_id)
    assert_problem(client.post("/v1/rooms/nope/epochs", json={}, headers=TERMINAL), 404)
    base = f"/v1/rooms/{room_id}/epochs"
    assert_problem(client.get(f"{base}/nope", headers=TERMINAL), 404)
    assert_problem(client.post(f"{base}/nope/solve", headers=TERMINAL), 404)
    body = {"terminal_id": "t1", "amplitudes": [1.0] * 16}
    assert_problem(client.post(f"{base}/nope/measurements", json=body, headers=TERMINAL), 404)
    other = client.post("/v1/rooms", json=paper_layout().to_mapping(), headers=ADMIN).json()
    assert_problem(client.get(f"/v1/rooms/{other['id']}/epochs/{epoch['id']}", headers=ADMIN), 404)
    assert_problem(client.get(f"{base}/{epoch['id']}"), 401)
    assert_problem(client.post(base, json={}, headers={"X-API-Key": "wrong"}), 401)
    assert client.post(base, headers=ADMIN).status_code == 201  # no body: all defaults


def test_a_room_without_fingerprint_cannot_open_an_epoch(client: TestClient) -> None:
    room = client.post("/v1/rooms", json=paper_layout().to_mapping(), headers=ADMIN).json()
    response = client.post(f"/v1/rooms/{room['id']}/epochs", json={}, headers=TERMINAL)
    assert_problem(response, 409)


def test_terminal_cap_and_min_terminals_above_it(tmp_path: Path, database_url: str) -> None:
    capped = start(tmp_path / "data", database_url, epoch_max_terminals=2)
    try:
        room_id = room_of(capped)
        response = capped.post(
            f"/v1/rooms/{room_id}/epochs", json={"min_terminals": 3}, headers=TERMINAL
        )
        assert_problem(response, 422, ["body.min_terminals"])
        epoch = create(capped, room_id)
        amplitudes = terminal_amplitudes(seed=6)
        assert post(capped, epoch, "t1", amplitudes[0]).status_code == 202
        assert post(capped, epoch, "t2", amplitudes[1]).status_code == 202
        assert "maximum" in assert_problem(post(capped, epoch, "t3", amplitudes[2]), 409)["detail"]
        assert post(capped, epoch, "t1", amplitudes[0]).status_code == 202  # replacing is fine
    finally:
        capped.__exit__(None, None, None)


def test_a_crashing_solver_fails_the_epoch_instead_of_sticking(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*_args: object, **_kwargs: object) -> None:
        raise SolverError("the solver diverged")

    monkeypatch.setattr(app.services.epoch_settler, "localize_terminals", broken)
    epoch = create(client, room_of(client))
    for name, row in zip(["t1", "t2"], terminal_amplitudes(seed=7)[:2], strict=True):
        post(client, epoch, name, row)
    failed = solve(client, epoch)
    assert failed["status"] == "failed" and failed["error"] == "the solver diverged"
    assert read(client, epoch) == failed


def test_epochs_survive_a_restart(tmp_path: Path, database_url: str) -> None:
    amplitudes = terminal_amplitudes(seed=8)
    clock = FakeClock()
    first = start(tmp_path / "data", database_url, clock)
    try:
        epoch = create(first, room_of(first), window_s=60)
        assert post(first, epoch, "t1", amplitudes[0]).status_code == 202
    finally:
        first.__exit__(None, None, None)
    second = start(tmp_path / "data", database_url, clock)
    try:
        assert read(second, epoch)["terminals"] == 1
        for name, row in zip(["t2", "t3"], amplitudes[1:], strict=True):
            assert post(second, epoch, name, row).status_code == 202
        assert_labelled_near_truth(solve(second, epoch), ["t1", "t2", "t3"])
    finally:
        second.__exit__(None, None, None)


def settled(client: TestClient, status: str) -> float:
    """How many epochs this app's process settled with ``status`` (its Prometheus counter)."""
    value = service(client).state.metrics.registry.get_sample_value(
        "vlp_epochs_settled_total", {"status": status}
    )
    return float(value or 0.0)


@pytest.mark.postgres
def test_two_processes_share_one_epoch_and_solve_it_once(tmp_path: Path, postgres_url: str) -> None:
    clock = FakeClock()
    apps = [start(tmp_path / "data", postgres_url, clock) for _ in range(2)]
    try:
        epoch = create(apps[0], room_of(apps[0]))
        amplitudes = terminal_amplitudes(seed=9)
        for index, name in enumerate(["t1", "t2", "t3"]):
            assert post(apps[index % 2], epoch, name, amplitudes[index]).status_code == 202
        answers: list[dict[str, Any]] = []
        barrier = threading.Barrier(4)

        def call_solve(client: TestClient) -> None:
            barrier.wait()
            answers.append(solve(client, epoch))

        threads = [threading.Thread(target=call_solve, args=(c,)) for c in apps + apps]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        assert len(answers) == 4 and all(answer == answers[0] for answer in answers)
        assert answers[0]["status"] == "solved"
        assert_labelled_near_truth(answers[0], ["t1", "t2", "t3"])
        assert sum(settled(c, "solved") for c in apps) == 1
        registry = registry_of(apps[1])
        assert registry.epochs.get(room_id=epoch["room_id"], epoch_id=epoch["id"]).attempts == 1
    finally:
        for test_client in apps:
            test_client.__exit__(None, None, None)


def test_the_sweeper_closes_passed_windows_without_any_request(
    tmp_path: Path, database_url: str
) -> None:
    swept = start(tmp_path / "data", database_url, epoch_sweep_seconds=0.05)
    try:
        epoch = create(swept, room_of(swept), window_s=1.0)
        for name, row in zip(["t1", "t2", "t3"], terminal_amplitudes(seed=10), strict=True):
            assert post(swept, epoch, name, row).status_code == 202
        registry = registry_of(swept)
        ids = {"room_id": epoch["room_id"], "epoch_id": epoch["id"]}
        let_window_pass(swept, epoch)
        wait_for(
            lambda: registry.epochs.get(**ids).status not in ("open", "solving"),
            "the sweeper to close the passed window",
        )
        assert registry.epochs.get(**ids).status == "solved"
        # The sweeper counts an outcome after storing it: the count may come a moment later.
        wait_for(lambda: settled(swept, "solved") >= 1, "the sweeper to count its outcome")
        assert settled(swept, "solved") == 1
        assert_labelled_near_truth(read(swept, epoch), ["t1", "t2", "t3"])
    finally:
        swept.__exit__(None, None, None)


def test_a_sweep_purges_epochs_past_their_retention(tmp_path: Path, database_url: str) -> None:
    brief = start(tmp_path / "data", database_url, epoch_retention_seconds=0.001)
    try:
        epoch = create(brief, room_of(brief))
        kept = create(brief, room_of(brief))
        assert solve(brief, epoch)["status"] == "expired"
        clock_of(brief).advance(0.5)  # past its retention, not past the other's 2 s window
        service(brief).state.epoch_settler.sweep()
        gone = brief.get(f"/v1/rooms/{epoch['room_id']}/epochs/{epoch['id']}", headers=TERMINAL)
        assert_problem(gone, 404)
        assert read(brief, kept)["status"] == "open"
    finally:
        brief.__exit__(None, None, None)


def test_the_swagger_examples_solve_the_demo_room(client: TestClient) -> None:
    room_id = room_of(client)
    response = client.post(
        f"/v1/rooms/{room_id}/epochs",
        json=epoch_create_examples()["by-hand"]["value"],
        headers=TERMINAL,
    )
    assert response.status_code == 201, response.text
    epoch = response.json()
    url = f"/v1/rooms/{room_id}/epochs/{epoch['id']}/measurements"
    for example in epoch_measurement_examples().values():
        assert client.post(url, json=example["value"], headers=TERMINAL).status_code == 202
    solved = solve(client, epoch)
    # The examples are the noiseless amplitudes at (1.0, 1.2) m (t1) and (2.9, 3.1) m (t2).
    where = {e["terminal_id"]: (e["x"], e["y"]) for e in solved["localization"]["estimates"]}
    assert where.keys() == {"t1", "t2"}
    assert math.dist(where["t1"], (1.0, 1.2)) < 0.05 and math.dist(where["t2"], (2.9, 3.1)) < 0.05


def test_an_epoch_whose_solver_died_is_taken_over_when_its_claim_runs_out(
    client: TestClient,
) -> None:
    epoch = create(client, room_of(client))
    for name, row in zip(["t1", "t2", "t3"], terminal_amplitudes(seed=11), strict=True):
        post(client, epoch, name, row)
    ids = {"room_id": epoch["room_id"], "epoch_id": epoch["id"]}
    # Another process claimed it and died: its claim (a lease) runs out after 1 s.
    clock = clock_of(client)
    dead = registry_of(client).epochs.claim(
        **ids,
        owner="dead-process",
        now=clock.now(),
        lease_s=1.0,
        max_attempts=3,
        force=True,
    )
    assert dead is not None
    being_solved = read(client, epoch)
    assert (being_solved["status"], being_solved["closed"]) == ("open", True)
    assert_problem(post(client, epoch, "t4", terminal_amplitudes(seed=11)[0]), 409)
    clock.advance(1.0)  # the dead process's lease runs out
    solved = solve(client, epoch)
    assert solved["status"] == "solved"
    assert_labelled_near_truth(solved, ["t1", "t2", "t3"])
    assert registry_of(client).epochs.get(**ids).attempts == 2


def test_an_epoch_above_the_work_limit_fails_naming_the_limit(
    tmp_path: Path, database_url: str
) -> None:
    """VLP_MAX_LOCALIZE_WORK bounds an epoch's solve as it bounds localize: the paper room
    (400 points, 16 LEDs) with a limit of 400 x 16 x 2 solves two terminals fitted on their
    own, and fails (without solving) an epoch of three."""
    client = start(tmp_path / "data", database_url, max_localize_work=400 * 16 * 2)
    try:
        room_id = room_of(client)
        amplitudes = terminal_amplitudes(seed=3)
        two = create(client, room_id, window_s=60)
        for name, row in zip(["t1", "t2"], amplitudes, strict=False):
            assert post(client, two, name, row).status_code == 202
        assert solve(client, two)["status"] == "solved"
        three = create(client, room_id, window_s=60)
        for name, row in zip(["t1", "t2", "t3"], amplitudes, strict=True):
            assert post(client, three, name, row).status_code == 202
        failed = solve(client, three)
        assert failed["status"] == "failed" and failed["localization"] is None
        assert "VLP_MAX_LOCALIZE_WORK" in failed["error"] and "19200" in failed["error"]
    finally:
        client.__exit__(None, None, None)


def test_undetected_leds_post_as_null_and_solve_as_localize_censors_them(
    client: TestClient,
) -> None:
    """Null amplitudes and a terminal's own floor reach the epoch's solve unchanged: it
    answers what localize answers for the same terminals (the same censored fit)."""
    clean = true_amplitudes(paper_layout(), TRUTH)
    floor = 0.25 * float(clean.max())
    sent = np.where(clean < floor, np.nan, clean)
    assert np.isnan(sent).sum(axis=1).min() >= 6  # most LEDs are not detected
    names = ["t1", "t2", "t3"]
    floors: list[float | None] = [floor, None, floor]  # t2 leaves its floor to the service
    terminals = [
        {
            "id": name,
            "amplitudes": [None if np.isnan(a) else float(a) for a in row],
            **({} if own is None else {"detection_floor": own}),
        }
        for name, row, own in zip(names, sent, floors, strict=True)
    ]
    room_id = room_of(client)
    epoch = create(client, room_id, window_s=60, track=False)
    for terminal in terminals:
        body = {"terminal_id": terminal["id"], **{k: v for k, v in terminal.items() if k != "id"}}
        response = client.post(
            f"/v1/rooms/{room_id}/epochs/{epoch['id']}/measurements", json=body, headers=TERMINAL
        )
        assert response.status_code == 202, response.text
    solved = solve(client, epoch)
    assert solved["status"] == "solved", solved
    assert_labelled_near_truth(solved, names)

    def positions(terminals: list[dict[str, Any]]) -> dict[str, tuple[float, float]]:
        response = client.post(
            f"/v1/rooms/{room_id}/localize", json={"terminals": terminals}, headers=TERMINAL
        )
        assert response.status_code == 200, response.text
        return {e["terminal_id"]: (e["x"], e["y"]) for e in response.json()["estimates"]}

    by_epoch = {e["terminal_id"]: (e["x"], e["y"]) for e in solved["localization"]["estimates"]}
    by_localize = positions(terminals)
    for name in names:
        assert by_epoch[name] == pytest.approx(by_localize[name], abs=1e-6)
    # The floors sent matter (without them localize answers otherwise), so the epoch kept them.
    floorless = positions(
        [{k: v for k, v in t.items() if k != "detection_floor"} for t in terminals]
    )
    assert max(math.dist(floorless[name], by_localize[name]) for name in ("t1", "t3")) > 1e-4, (
        "the floors sent should change the fit; the comparison above would not see them"
    )
