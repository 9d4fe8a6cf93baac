"""Concurrency against real processes: localize during rebuilds and replacements, racing
admins, and two ``vlp worker`` processes sharing one queue (SQLite and PostgreSQL)."""

from __future__ import annotations

import operator
import threading
from collections import Counter
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest
from numpy.testing import assert_allclose

from app.registry import Registry
from app.registry.errors import PreconditionFailed
from app.vlp.measurements import measurement_from_power
from app.vlp.solvers import make_solver
from tests.build_gate import BuildGate
from tests.db_fixtures import hall_layout, small_layout
from tests.processes import TERMINAL, VlpProcess, process_fleet
from tests.waiting import wait_for

from .checks import assert_nothing_lost, registry_of
from .steps import MID_BUILD

pytestmark = pytest.mark.slow

N_LOCALIZERS = 4
N_LAYOUT_CHANGES = 6


def mirrored_layouts() -> tuple[dict[str, Any], dict[str, Any]]:
    """Two layouts of one 3 x 3 m room with 4 LEDs each, at different places.

    The same power measurement is valid for both (M = 4) but localizes differently, so an
    answer computed from one version's matrices and labelled with another's would show.
    """
    room = {"room": {"length": 3.0, "width": 3.0, "height": 3.0}}
    grid = {"grid": {"step": 0.25, "receiver_height": 0.85}}

    def layout(name: str, leds: list[tuple[float, float]]) -> dict[str, Any]:
        return {"name": name, **room, **grid, "leds": [{"x": x, "y": y} for x, y in leds]}

    return (
        layout("first", [(0.6, 0.6), (2.4, 0.6), (0.6, 2.4), (2.4, 2.4)]),
        layout("second", [(1.0, 0.4), (2.6, 1.0), (2.0, 2.6), (0.4, 2.0)]),
    )


def put_room(client: httpx.Client, room_id: str, layout: dict[str, Any]) -> int:
    """Replace the room with the current ETag; returns the new layout version."""
    room = client.get(f"/v1/rooms/{room_id}")
    response = client.put(
        f"/v1/rooms/{room_id}", json=layout, headers={"If-Match": room.headers["ETag"]}
    )
    assert response.status_code == 200, response.text
    return int(response.json()["layout_version"])


def current_version(client: httpx.Client, room_id: str) -> int | None:
    """The version localization uses now."""
    version = client.get(f"/v1/rooms/{room_id}").json()["fingerprint"]["version"]
    return None if version is None else int(version)


def churn(
    server: VlpProcess, room_id: str, layouts: tuple[dict[str, Any], ...], answered: set[int]
) -> None:
    """Alternately replace the layout and rebuild the same one; after each change, wait until
    the new version is current and a localize answer has named it (``answered``)."""
    with server.client() as client:
        for change in range(N_LAYOUT_CHANGES):
            before = current_version(client, room_id) or 0
            if change % 2:
                response = client.post(f"/v1/rooms/{room_id}/fingerprints")
                assert response.status_code == 202, response.text
            else:
                put_room(client, room_id, layouts[(change // 2 + 1) % 2])
            wait_for(
                partial(newer_than, client, room_id, before), "the new version to become current"
            )
            version = current_version(client, room_id)
            named = partial(operator.contains, answered, version)
            wait_for(named, f"a localize answer naming version {version}")


def newer_than(client: httpx.Client, room_id: str, version: int) -> bool:
    """True once the room's current version is above ``version``."""
    return (current_version(client, room_id) or 0) > version


def localize_until(
    server: VlpProcess,
    room_id: str,
    body: dict[str, Any],
    stop: threading.Event,
    answered: set[int],
) -> list[dict[str, Any]]:
    """Localize in a loop until ``stop``; every answer must be 200. Adds the version each
    answer names to ``answered``."""
    answers = []
    with httpx.Client(base_url=server.url, headers=TERMINAL, timeout=30.0) as client:
        while not stop.is_set():
            response = client.post(f"/v1/rooms/{room_id}/localize", json=body)
            assert response.status_code == 200, response.text
            answers.append(response.json())
            answered.add(int(answers[-1]["fingerprint_version"]))
    return answers


def test_each_localize_answer_matches_the_version_it_names(tmp_path: Path) -> None:
    layouts = mirrored_layouts()
    env = {"VLP_DEMO": "0", "VLP_EMBEDDED_WORKERS": "1", "VLP_VERSION_CHECK_SECONDS": "0"}
    with process_fleet(tmp_path / "data", **env) as fleet:
        server = fleet.serve()
        with server.client() as client:
            room_id = client.post("/v1/rooms", json=layouts[0]).json()["id"]
            wait_for(lambda: current_version(client, room_id) == 1, "version 1")
            positions = [[0.875, 1.125], [2.125, 2.375]]
            simulated = client.post(
                f"/v1/rooms/{room_id}/simulate",
                json={"positions": positions, "model": "power", "solver": "nnls", "seed": 3},
            )
            assert simulated.status_code == 200, simulated.text
        # Unpinned: each request takes whatever version is current when it is served.
        body = {**simulated.json()["measurement"], "targets": 2, "fingerprint_version": None}
        stop = threading.Event()
        answered: set[int] = set()
        results: list[list[dict[str, Any]]] = [[] for _ in range(N_LOCALIZERS)]
        errors: list[BaseException] = []

        def localizer(index: int) -> None:
            try:
                results[index] = localize_until(server, room_id, body, stop, answered)
            except BaseException as exc:  # reported below, in the test's thread
                errors.append(exc)
                raise

        threads = [threading.Thread(target=localizer, args=(i,)) for i in range(N_LOCALIZERS)]
        for thread in threads:
            thread.start()
        try:
            churn(server, room_id, layouts, answered)
        finally:
            stop.set()
            for thread in threads:
                thread.join(60)
        assert not errors, errors
        answers = [answer for per_thread in results for answer in per_thread]
        registry = registry_of(fleet.data_dir)
        try:
            check_answers(registry, room_id, body, answers)
        finally:
            registry.dispose()


def check_answers(
    registry: Registry, room_id: str, body: dict[str, Any], answers: list[dict[str, Any]]
) -> None:
    """Each answer equals nnls run here on the stored matrices of the version it names."""
    by_version = Counter(answer["fingerprint_version"] for answer in answers)
    # The answers span rebuilds and replacements (churn waited for each version's answer).
    assert len(by_version) == 1 + N_LAYOUT_CHANGES, by_version
    expected = {}
    for version in by_version:
        fingerprint = registry.load_fingerprint(room_id=room_id, version=version)
        solution = make_solver("nnls", fingerprint, "power").solve(
            measurement_from_power(body["power"], fingerprint.n_leds), 2
        )
        expected[version] = (solution.positions, solution.grid_indices.tolist())
    distinct = {tuple(indices) for _, indices in expected.values()}
    assert len(distinct) >= 2, "the versions must localize differently for this to test"
    for answer in answers:
        positions, indices = expected[answer["fingerprint_version"]]
        got = [[e["x"], e["y"]] for e in answer["estimates"]]
        assert [e["grid_index"] for e in answer["estimates"]] == indices, answer
        assert_allclose(got, positions, rtol=0, atol=1e-9)


def test_two_admins_race_one_wins_the_other_gets_412(tmp_path: Path) -> None:
    contenders = 6
    with process_fleet(tmp_path / "data", VLP_DEMO="0", VLP_EMBEDDED_WORKERS="0") as fleet:
        server = fleet.serve()
        with server.client() as client:
            created = client.post("/v1/rooms", json={"name": "before", **small_layout()})
            etag = created.headers["ETag"]
        barrier = threading.Barrier(contenders)
        statuses: dict[str, httpx.Response] = {}

        def admin(name: str) -> None:
            with server.client() as client:
                barrier.wait(30)
                statuses[name] = client.put(
                    f"/v1/rooms/{created.json()['id']}",
                    json={"name": name, **small_layout(3)},
                    headers={"If-Match": etag},
                )

        threads = [threading.Thread(target=admin, args=(f"admin-{i}",)) for i in range(contenders)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        codes = Counter(response.status_code for response in statuses.values())
        assert codes == {200: 1, 412: contenders - 1}, codes
        (winner,) = [name for name, response in statuses.items() if response.status_code == 200]
        for response in statuses.values():
            if response.status_code == 412:
                assert response.headers["content-type"] == "application/problem+json"
        with server.client() as client:
            room = client.get(f"/v1/rooms/{created.json()['id']}").json()
        assert (room["name"], room["layout_version"], len(room["layout"]["leds"])) == (
            winner,
            2,
            3,
        )


def test_racing_replacements_one_wins_per_version(registry: Registry) -> None:
    """Registry level, both backends: of N writers expecting one version, exactly one wins."""
    room = registry.create_room(name="r", layout=small_layout())
    contenders = 8
    barrier = threading.Barrier(contenders)
    outcomes: list[str] = []

    def writer(index: int) -> None:
        barrier.wait(30)
        try:
            registry.replace_room(
                room_id=room.id,
                name=f"w{index}",
                layout=small_layout(1 + index % 3),
                expected_layout_version=1,
            )
            outcomes.append(f"w{index}")
        except PreconditionFailed:
            outcomes.append("412")

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(contenders)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    winners = [outcome for outcome in outcomes if outcome != "412"]
    assert len(outcomes) == contenders and len(winners) == 1
    stored = registry.get_room(room_id=room.id)
    assert (stored.name, stored.layout_version) == (winners[0], 2)


def test_two_worker_processes_never_build_the_same_job(database_url: str, tmp_path: Path) -> None:
    """Eight rooms, two workers: each job is built once. The first build is held at the
    gate, so the other worker (one build thread each) surely takes jobs too."""
    data_dir = tmp_path / "data"
    gate = BuildGate(tmp_path / "gate", at=MID_BUILD)
    with process_fleet(data_dir, VLP_DATABASE_URL=database_url, **gate.env()) as fleet:
        workers = [fleet.worker(), fleet.worker()]
        registry = registry_of(data_dir, database_url)
        try:
            wait_for(registry.migrations_current, "the workers to migrate")
            gate.shut()
            rooms = [registry.create_room(name="hall 0", layout=hall_layout().to_mapping())]
            assert gate.wait_held() == rooms[0].job_id
            rooms += [
                registry.create_room(name=f"hall {i}", layout=hall_layout().to_mapping())
                for i in range(1, 8)
            ]
            wait_for(
                lambda: all(
                    registry.get_room(room_id=room.id).fingerprint_status == "ready"
                    for room in rooms[1:]
                ),
                "the other worker to build the rooms after the held one",
                300,
            )
            gate.open()
            wait_for(
                lambda: all(
                    registry.get_room(room_id=room.id).fingerprint_status == "ready"
                    for room in rooms
                ),
                "every room to be built",
                300,
            )
            built_by = [
                {
                    entry["job_id"]
                    for entry in worker.log()
                    if entry.get("message", "").startswith("job ")
                    and "building" in entry["message"]
                }
                for worker in workers
            ]
            jobs = {room.job_id for room in rooms}
            assert built_by[0] | built_by[1] == jobs
            assert not built_by[0] & built_by[1], "a job was built by both workers"
            assert all(built_by), f"one worker built everything: {built_by}"
            for room in rooms:
                assert registry.get_job(job_id=room.job_id or "").attempts == 1
                assert [fp.version for fp in registry.list_fingerprints(room_id=room.id)] == [1]
            assert_nothing_lost(registry, rooms={room.id: 1 for room in rooms})
        finally:
            registry.dispose()
