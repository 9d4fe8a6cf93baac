"""``kill -9`` of a real ``vlp serve`` in the middle of building the 10^6-point hall (SQLite).

The worker-process death on PostgreSQL is in ``test_scale_out.py``.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from app.vlp.presets import paper_layout
from tests.build_gate import BuildGate
from tests.db_fixtures import million_point_hall, overwrite
from tests.processes import VlpProcess, peak_rss_bytes, process_fleet

from .checks import assert_nothing_lost, registry_of
from .steps import (
    HALL_TIMEOUT_S,
    MID_BUILD,
    assert_orphans_exit,
    create_room,
    kill_mid_build,
    wait_succeeded,
)

pytestmark = pytest.mark.slow


def corrupt_then_repaired(server: VlpProcess, room_id: str) -> None:
    """Flip bytes of a stored matrix (same size): 503 naming the hash, then the rebuild that
    answer queued heals it.

    The test waits for that rebuild job to succeed, not for the download to heal: the build
    writes the file before its job is recorded, so a healed download alone does not mean
    the job has finished (nothing may be left ``running`` afterwards)."""
    with server.client() as client:
        meta = client.get(f"/v1/rooms/{room_id}/fingerprints/current").json()
        sha = meta["matrices"]["H"]["sha256"]
        path = server.data_dir / "matrices" / sha[:2] / f"{sha}.npy"
        payload = bytearray(path.read_bytes())
        payload[-64:] = bytes(255 - b for b in payload[-64:])
        overwrite(path, bytes(payload))
        url = f"/v1/rooms/{room_id}/fingerprints/{meta['version']}/H.npy"
        refused = client.get(url)
        assert refused.status_code == 503, refused.text
        assert refused.headers["content-type"] == "application/problem+json"
        assert "sha256" in refused.json()["detail"]
        # The refusal queued the rebuild: it is the room's latest job (in whatever state).
        wait_succeeded(server, client.get(f"/v1/rooms/{room_id}").json()["fingerprint"]["job_id"])
        healed = client.get(url)
        assert healed.status_code == 200, healed.text
        assert hashlib.sha256(healed.content).hexdigest() == sha


def test_kill9_server_mid_hall_build_then_restart_finishes(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    env = {"VLP_DEMO": "0", "VLP_EMBEDDED_WORKERS": "1"}
    gate = BuildGate(tmp_path / "gate", at=MID_BUILD)
    with process_fleet(data_dir, **env) as fleet:
        first = fleet.serve(gate.env())
        paper = create_room(first, paper_layout().to_mapping())
        paper_done = wait_succeeded(first, paper["fingerprint"]["job_id"])
        gate.shut()
        hall = create_room(first, million_point_hall().to_mapping())
        hall_job = hall["fingerprint"]["job_id"]
        orphans = kill_mid_build(first, first, hall_job, gate)
        assert_orphans_exit(orphans)

        registry = registry_of(data_dir)
        try:
            stuck = registry.get_job(job_id=hall_job)
            assert (stuck.status, stuck.attempts) == ("running", 1)  # the dead owner's lease
            second = fleet.serve()
            finished = wait_succeeded(second, hall_job, HALL_TIMEOUT_S)
            assert finished["result"]["fingerprint_version"] == 1
            assert registry.get_job(job_id=hall_job).attempts == 2
            # The pool keeps its child after the build, so its peak covers the whole hall
            # build; server and children together (an upper bound) stay below 2 GiB.
            peaks = [peak_rss_bytes(pid) for pid in [second.pid, *second.build_children()]]
            assert sum(peaks) < 2 * 1024**3, f"peak resident memory {peaks} bytes"
            meta = registry.get_fingerprint(room_id=hall["id"], version=None)
            assert (meta.leds, meta.grid_points, meta.matrices["H"].format) == (
                1024,
                1_000_000,
                "npz",
            )
            assert_nothing_lost(
                registry,
                rooms={paper["id"]: paper_done["result"]["fingerprint_version"], hall["id"]: 1},
            )
            corrupt_then_repaired(second, paper["id"])
            assert_nothing_lost(registry, rooms={paper["id"]: 2, hall["id"]: 1})
        finally:
            registry.dispose()
