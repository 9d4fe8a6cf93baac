"""Scale-out across machines: two ``vlp serve`` and one ``vlp worker`` that share only the
PostgreSQL server, each with its own ``VLP_DATA_DIR`` (as on three hosts with no shared
filesystem). Both APIs serve the same rooms, matrix downloads and localizations, because the
matrices live in the database (``VLP_MATRIX_STORE=auto`` on PostgreSQL).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import pytest

from app.schemas.rooms import paper_room_example
from tests.processes import TERMINAL, VlpProcess, process_fleet

from .steps import create_room, wait_succeeded

pytestmark = [pytest.mark.slow, pytest.mark.postgres]


def matrix_files(data_dir: Path) -> list[Path]:
    """The matrix files under a data directory."""
    return sorted((data_dir / "matrices").rglob("*.np[yz]"))


def localization(api: VlpProcess, room_id: str, measurement: dict[str, Any]) -> dict[str, Any]:
    """The answer of ``api`` to a localize request, without its timing."""
    with api.client() as client:
        response = client.post(f"/v1/rooms/{room_id}/localize", json=measurement, headers=TERMINAL)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    body.pop("elapsed_ms")
    return body


def test_two_apis_and_a_worker_sharing_only_postgresql_serve_the_same_rooms(
    postgres_url: str, tmp_path: Path
) -> None:
    dirs = {name: tmp_path / name for name in ("api-a", "api-b", "worker")}
    env = {"VLP_DATABASE_URL": postgres_url, "VLP_DEMO": "0", "VLP_EMBEDDED_WORKERS": "0"}
    with process_fleet(tmp_path / "fleet", **env) as fleet:
        apis = [
            fleet.serve({"VLP_DATA_DIR": str(dirs["api-a"])}),
            fleet.serve({"VLP_DATA_DIR": str(dirs["api-b"])}),
        ]
        fleet.worker(VLP_DATA_DIR=str(dirs["worker"]))
        room = create_room(apis[0], paper_room_example())
        wait_succeeded(apis[1], room["fingerprint"]["job_id"])
        assert matrix_files(dirs["worker"]), "the worker built nothing"
        assert not matrix_files(dirs["api-a"]) and not matrix_files(dirs["api-b"])

        listed = []
        for api in apis:
            with api.client() as client:
                listed.append([item["id"] for item in client.get("/v1/rooms").json()["items"]])
        assert listed == [[room["id"]], [room["id"]]]

        with apis[0].client() as client:
            meta = client.get(f"/v1/rooms/{room['id']}/fingerprints/current").json()
            simulated = client.post(
                f"/v1/rooms/{room['id']}/simulate",
                json={"targets": 3, "snr_db": 40, "seed": 11},
                headers=TERMINAL,
            )
        assert simulated.status_code == 200, simulated.text
        for name, info in meta["matrices"].items():
            url = f"/v1/rooms/{room['id']}/fingerprints/{meta['version']}/{name}.{info['format']}"
            for api in apis:
                with api.client() as client:
                    download = client.get(url)
                assert download.status_code == 200, (api.url, name, download.text)
                assert hashlib.sha256(download.content).hexdigest() == info["sha256"]
        measurement = simulated.json()["measurement"]
        answers = [localization(api, room["id"], measurement) for api in apis]
        assert answers[0] == answers[1]
        assert answers[0]["targets"] == 3


def test_with_local_files_only_the_other_hosts_cannot_serve_the_matrices(
    postgres_url: str, tmp_path: Path
) -> None:
    # The control: the same hosts with VLP_MATRIX_STORE=files refuse the download (503,
    # rebuild queued), so the test above passes because of the database store.
    env = {
        "VLP_DATABASE_URL": postgres_url,
        "VLP_DEMO": "0",
        "VLP_EMBEDDED_WORKERS": "0",
        "VLP_MATRIX_STORE": "files",
    }
    with process_fleet(tmp_path / "fleet", **env) as fleet:
        api = fleet.serve({"VLP_DATA_DIR": str(tmp_path / "api")})
        fleet.worker(VLP_DATA_DIR=str(tmp_path / "worker"))
        room = create_room(api, paper_room_example())
        wait_succeeded(api, room["fingerprint"]["job_id"])
        with api.client() as client:
            download = client.get(f"/v1/rooms/{room['id']}/fingerprints/current/H.npy")
        assert download.status_code == 503, download.text
        assert "sha256" in download.json()["detail"]
