"""Scale-out for real: two ``vlp serve`` and two ``vlp worker`` processes on one PostgreSQL.

Builds are shared between the workers (one build is held at the test's gate, so the other
worker must take the rest), a rebuild is seen by both API processes (their version re-read
interval is 1 s; ``tests/api/test_localize.py`` checks that interval on a stepped clock, here
only a safety timeout bounds the wait), and ``kill -9`` of the worker building the
10^6-point hall, held mid-build at the gate, is survived: the job is reclaimed when its lease
ends and finishes.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import pytest

from tests.build_gate import BuildGate
from tests.db_fixtures import hall_layout, million_point_hall, small_layout
from tests.processes import TERMINAL, VlpProcess, process_fleet
from tests.waiting import wait_for

from .checks import assert_nothing_lost, registry_of
from .steps import (
    HALL_TIMEOUT_S,
    MID_BUILD,
    assert_orphans_exit,
    create_room,
    kill_mid_build,
    wait_succeeded,
)

pytestmark = [pytest.mark.slow, pytest.mark.postgres]


def jobs_built_by(worker: VlpProcess) -> list[str]:
    """Job ids the worker started building, in order (from its JSON log)."""
    return [
        entry["job_id"]
        for entry in worker.log()
        if entry.get("message", "").startswith("job ") and "building" in entry["message"]
    ]


def localized_version(api: VlpProcess, room_id: str) -> int:
    """The fingerprint version a localize answer from ``api`` names."""
    # Powers of the small room's own scale: 100x above it is refused as other units.
    body = {"power": [1e-10, 2e-10, 1e-10, 3e-10], "targets": 1, "solver": "nnls"}
    with api.client() as client:
        response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    return int(response.json()["fingerprint_version"])


def assert_builds_shared(
    apis: list[VlpProcess], workers: list[VlpProcess], gate: BuildGate
) -> list[str]:
    """Six rooms posted through both APIs are built once each, by both workers: the first
    build is held at the gate, so its worker (one build thread) is busy while the other one
    builds the remaining five; then the gate opens."""
    gate.shut()
    rooms = [create_room(apis[0], {**hall_layout().to_mapping(), "name": "hall 0"})]
    assert gate.wait_held() == rooms[0]["fingerprint"]["job_id"]
    rooms += [
        create_room(apis[i % 2], {**hall_layout().to_mapping(), "name": f"hall {i}"})
        for i in range(1, 6)
    ]
    for i, room in enumerate(rooms[1:], start=1):
        wait_succeeded(apis[(i + 1) % 2], room["fingerprint"]["job_id"])
    gate.open()
    wait_succeeded(apis[1], rooms[0]["fingerprint"]["job_id"])
    built = [set(jobs_built_by(worker)) for worker in workers]
    assert built[0] | built[1] == {room["fingerprint"]["job_id"] for room in rooms}
    assert not built[0] & built[1], "a job was built by both workers"
    assert built[0] and built[1], f"one worker built everything: {built}"
    return [str(room["id"]) for room in rooms]


def assert_rebuild_seen_by_both(apis: list[VlpProcess], room_id: str) -> None:
    """After a rebuild finishes, both API processes localize with it (the re-read interval's
    timing is tested on a stepped clock in tests/api/test_localize.py)."""
    assert [localized_version(api, room_id) for api in apis] == [1, 1]
    with apis[0].client() as client:
        response = client.post(f"/v1/rooms/{room_id}/fingerprints")
    assert response.status_code == 202, response.text
    done = wait_succeeded(apis[1], response.json()["id"])
    assert done["result"]["fingerprint_version"] == 2
    for index, api in enumerate(apis):
        wait_for(partial(on_version, api, room_id, 2), f"API {index} to localize with version 2")


def on_version(api: VlpProcess, room_id: str, version: int) -> bool:
    """True when a localize answer of ``api`` names ``version``."""
    return localized_version(api, room_id) == version


def test_two_apis_two_workers_share_builds_see_rebuilds_survive_a_worker_death(
    postgres_url: str, tmp_path: Path
) -> None:
    env = {"VLP_DATABASE_URL": postgres_url, "VLP_DEMO": "0", "VLP_EMBEDDED_WORKERS": "0"}
    gate = BuildGate(tmp_path / "gate", at=MID_BUILD)
    with process_fleet(tmp_path / "data", **env) as fleet:
        apis = [fleet.serve(), fleet.serve()]
        workers = [fleet.worker(**gate.env()), fleet.worker(**gate.env())]
        halls = assert_builds_shared(apis, workers, gate)
        small = create_room(apis[0], {"name": "small", **small_layout(4)})
        wait_succeeded(apis[0], small["fingerprint"]["job_id"])
        assert_rebuild_seen_by_both(apis, small["id"])

        gate.shut()
        hall = create_room(apis[1], million_point_hall().to_mapping())
        hall_job = hall["fingerprint"]["job_id"]
        owner = owner_of(workers, hall_job)
        orphans = kill_mid_build(owner, apis[0], hall_job, gate)
        assert_orphans_exit(orphans)
        survivor = workers[1 - workers.index(owner)]
        replacement = fleet.worker()
        finished = wait_succeeded(apis[1], hall_job, HALL_TIMEOUT_S)
        assert finished["result"]["fingerprint_version"] == 1
        rebuilt_by = [w for w in (survivor, replacement) if hall_job in jobs_built_by(w)]
        assert len(rebuilt_by) == 1, "exactly one live worker took the job over"

        registry = registry_of(fleet.data_dir, postgres_url)
        try:
            assert registry.get_job(job_id=hall_job).attempts == 2
            rooms: dict[str, int | None] = dict.fromkeys(halls, 1)
            rooms |= {small["id"]: 2, hall["id"]: 1}
            assert registry.count_rooms() == len(rooms)
            assert_nothing_lost(registry, rooms=rooms)
        finally:
            registry.dispose()


def owner_of(workers: list[VlpProcess], job_id: str) -> VlpProcess:
    """The worker that claimed ``job_id`` (waits for its log line)."""
    found: list[VlpProcess] = []

    def claimed() -> bool:
        found[:] = [worker for worker in workers if job_id in jobs_built_by(worker)]
        return bool(found)

    wait_for(claimed, f"a worker to claim {job_id}")
    assert len(found) == 1
    return found[0]
