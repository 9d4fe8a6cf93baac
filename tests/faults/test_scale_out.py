"""Scale-out for real: two ``vlp serve`` and two ``vlp worker`` processes on one PostgreSQL.

Builds are shared between the workers, a rebuild is seen by both API processes within 2 s
(their version re-read interval is 1 s), and ``kill -9`` of the worker building the
10^6-point hall is survived: the job is reclaimed when its lease ends and finishes.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.db_fixtures import hall_layout, million_point_hall, small_layout
from tests.processes import TERMINAL, VlpProcess, process_fleet, wait_for

from .checks import assert_nothing_lost, registry_of
from .steps import HALL_TIMEOUT_S, assert_orphans_exit, create_room, kill_mid_build, wait_succeeded

pytestmark = [pytest.mark.slow, pytest.mark.postgres]

VISIBLE_WITHIN_S = 2.0


def jobs_built_by(worker: VlpProcess) -> list[str]:
    """Job ids the worker started building, in order (from its JSON log)."""
    return [
        entry["job_id"]
        for entry in worker.log()
        if entry.get("message", "").startswith("job ") and "building" in entry["message"]
    ]


def localized_version(api: VlpProcess, room_id: str) -> int:
    """The fingerprint version a localize answer from ``api`` names."""
    body = {"power": [1e-6, 2e-6, 1e-6, 3e-6], "targets": 1, "solver": "nnls"}
    with api.client() as client:
        response = client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    assert response.status_code == 200, response.text
    return int(response.json()["fingerprint_version"])


def assert_builds_shared(apis: list[VlpProcess], workers: list[VlpProcess]) -> list[str]:
    """Six rooms posted through both APIs are built once each, by both workers."""
    rooms = [
        create_room(apis[i % 2], {**hall_layout().to_mapping(), "name": f"hall {i}"})
        for i in range(6)
    ]
    for i, room in enumerate(rooms):
        wait_succeeded(apis[(i + 1) % 2], room["fingerprint"]["job_id"])
    built = [set(jobs_built_by(worker)) for worker in workers]
    assert built[0] | built[1] == {room["fingerprint"]["job_id"] for room in rooms}
    assert not built[0] & built[1], "a job was built by both workers"
    assert built[0] and built[1], f"one worker built everything: {built}"
    return [str(room["id"]) for room in rooms]


def assert_rebuild_seen_by_both(apis: list[VlpProcess], room_id: str) -> None:
    """After a rebuild finishes, both API processes localize with it within 2 s."""
    assert [localized_version(api, room_id) for api in apis] == [1, 1]
    with apis[0].client() as client:
        response = client.post(f"/v1/rooms/{room_id}/fingerprints")
    assert response.status_code == 202, response.text
    done = wait_succeeded(apis[1], response.json()["id"])
    assert done["result"]["fingerprint_version"] == 2
    finished = time.monotonic()
    pending = set(range(len(apis)))
    while pending:
        pending = {i for i in pending if localized_version(apis[i], room_id) != 2}
        assert time.monotonic() - finished < VISIBLE_WITHIN_S, f"APIs {pending} still on 1"
        time.sleep(0.05)


def test_two_apis_two_workers_share_builds_see_rebuilds_survive_a_worker_death(
    postgres_url: str, tmp_path: Path
) -> None:
    env = {"VLP_DATABASE_URL": postgres_url, "VLP_DEMO": "0", "VLP_EMBEDDED_WORKERS": "0"}
    with process_fleet(tmp_path / "data", **env) as fleet:
        apis = [fleet.serve(), fleet.serve()]
        workers = [fleet.worker(), fleet.worker()]
        halls = assert_builds_shared(apis, workers)
        small = create_room(apis[0], {"name": "small", **small_layout(4)})
        wait_succeeded(apis[0], small["fingerprint"]["job_id"])
        assert_rebuild_seen_by_both(apis, small["id"])

        hall = create_room(apis[1], million_point_hall().to_mapping())
        hall_job = hall["fingerprint"]["job_id"]
        owner = owner_of(workers, hall_job)
        orphans = kill_mid_build(owner, apis[0], hall_job)
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
