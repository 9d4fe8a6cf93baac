"""Operations: health, readiness, metrics, the OpenAPI file and the offline docs."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from app.cli import main as vlp_main
from app.cli import openapi_document
from app.registry.errors import RegistryUnavailable
from tests.live_server import bound_url, wait_until_healthy
from tests.waiting import SAFETY_TIMEOUT_S

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem

REPO = Path(__file__).resolve().parents[2]
OPENAPI_FILE = REPO / "openapi" / "openapi.json"
# Where `vlp` looks for a key when --key is not given.
_KEY_VARIABLES = ("VLP_API_KEY", "VLP_ADMIN_KEYS", "VLP_TERMINAL_KEYS")


def test_healthz_and_readyz(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready"}


def test_readyz_is_503_when_registry_is_down_or_not_migrated(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    registry: Any = client.app.state.registry  # type: ignore[attr-defined]
    monkeypatch.setattr(registry, "migrations_current", lambda: False)
    assert_problem(client.get("/readyz"), 503)

    def down() -> None:
        raise RegistryUnavailable("the registry database cannot be reached")

    monkeypatch.setattr(registry, "ping", down)
    problem = assert_problem(client.get("/readyz"), 503)
    assert problem["detail"] == "the registry database cannot be reached"
    assert client.get("/healthz").status_code == 200


def _sample(text: str, name: str, labels: dict[str, str]) -> float:
    for line in text.splitlines():
        if not line.startswith(name + "{"):
            continue
        found = dict(re.findall(r'(\w+)="([^"]*)"', line.rsplit(" ", 1)[0]))
        if all(found.get(key) == value for key, value in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    raise AssertionError(f"no sample {name}{labels}")


def test_metrics_by_route_template_solver_and_cache(ready_app: tuple[TestClient, str]) -> None:
    client, room_id = ready_app
    for _ in range(3):
        client.get(f"/v1/rooms/{room_id}", headers=TERMINAL)
    client.get("/v1/unknown/path")
    body = {"power": [1e-10] * 16, "solver": "nnls", "targets": 1}
    for _ in range(2):
        client.post(f"/v1/rooms/{room_id}/localize", json=body, headers=TERMINAL)
    response = client.get("/metrics")
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text
    assert (
        _sample(
            text,
            "vlp_http_requests_total",
            {"method": "GET", "route": "/v1/rooms/{room_id}", "status": "200"},
        )
        >= 3
    )
    assert _sample(text, "vlp_http_requests_total", {"route": "unmatched", "status": "404"}) >= 1
    assert room_id not in text
    assert (
        _sample(
            text,
            "vlp_http_request_duration_seconds_count",
            {"route": "/v1/rooms/{room_id}/localize"},
        )
        >= 2
    )
    assert (
        _sample(text, "vlp_localize_duration_seconds_count", {"solver": "nnls", "model": "power"})
        >= 2
    )
    assert _sample(text, "vlp_fingerprint_cache_total", {"result": "hit"}) >= 1
    assert _sample(text, "vlp_fingerprint_cache_total", {"result": "miss"}) >= 1
    # Jobs by status appear when the registry can count them.
    registry = client.app.state.registry  # type: ignore[attr-defined]
    assert ("vlp_jobs{" in text) == hasattr(registry, "count_jobs_by_status")


def test_openapi_file_is_current(client: TestClient) -> None:
    served = client.get("/openapi.json").json()
    document = json.dumps(served, sort_keys=True, indent=2) + "\n"
    assert document == openapi_document()
    assert OPENAPI_FILE.read_text(encoding="utf-8") == document, "run `vlp openapi`"
    assert vlp_main(["openapi", "--check", "--output", str(OPENAPI_FILE)]) == 0


def test_vlp_openapi_writes_and_checks(tmp_path: Path) -> None:
    target = tmp_path / "openapi.json"
    assert vlp_main(["openapi", "--check", "--output", str(target)]) == 1
    assert vlp_main(["openapi", "--output", str(target)]) == 0
    assert target.read_text(encoding="utf-8") == openapi_document()
    assert vlp_main(["openapi", "--check", "--output", str(target)]) == 0


def test_openapi_teaches_the_api() -> None:
    spec = json.loads(openapi_document())
    assert spec["components"]["securitySchemes"]["ApiKey"] == {
        "type": "apiKey",
        "in": "header",
        "name": "X-API-Key",
        "description": spec["components"]["securitySchemes"]["ApiKey"]["description"],
    }
    operation_ids = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            where = f"{method.upper()} {path}"
            assert operation.get("summary") and operation.get("tags"), where
            operation_ids.append(operation["operationId"])
            if path.startswith("/v1/"):
                assert operation["security"] == [{"ApiKey": []}], where
                assert "401" in operation["responses"], where
            for status, answer in operation["responses"].items():
                if status.startswith(("4", "5")):
                    assert "application/problem+json" in answer["content"], (where, status)
    assert len(operation_ids) == len(set(operation_ids))
    assert "create_room" in operation_ids and "localize" in operation_ids
    schemas = spec["components"]["schemas"]
    for name in ("RoomLayout", "Measurement", "SimulationRequest"):
        assert schemas[name]["examples"], name
    assert schemas["Measurement"]["properties"]["solver"]["enum"] == [
        "gridless",
        "nnls",
        "omp",
        "l1",
    ]
    assert "HTTPValidationError" not in schemas


def test_docs_work_offline(client: TestClient) -> None:
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        external = re.findall(r"""https?://[^\s"'<>)]+""", html)
        assert external == [], (page, external)
        assets = re.findall(r"""(?:src|href)=["'](/static-docs/[^"']+)["']""", html)
        assert any(asset.endswith(".js") for asset in assets), page
        for asset in assets:
            response = client.get(asset)
            assert response.status_code == 200, asset
            assert len(response.content) > 1000, asset
            if asset.endswith(".js"):
                assert "javascript" in response.headers["content-type"], asset
    assert "/openapi.json" in client.get("/docs").text


@pytest.mark.slow
def test_vlp_serve_logs_json_and_vlp_rooms_lists(tmp_path: Path) -> None:
    """A real `vlp serve` process on the port it picked: JSON log lines with request ids;
    `vlp rooms` reads it."""
    vlp = Path(sys.executable).with_name("vlp")
    port_file = tmp_path / "serve.port"
    env = {
        **os.environ,
        "VLP_DATA_DIR": str(tmp_path),
        "VLP_ADMIN_KEYS": ADMIN["X-API-Key"],
        "VLP_TERMINAL_KEYS": TERMINAL["X-API-Key"],
        "VLP_EMBEDDED_WORKERS": "0",
        "VLP_DEMO": "1",
    }
    log_path = tmp_path / "server.log"
    with log_path.open("wb") as log:
        server = subprocess.Popen(
            [str(vlp), "serve", "--port", "0", "--port-file", str(port_file)],
            env=env,
            stdout=log,
            stderr=log,
        )
        try:
            url = bound_url(port_file, server, timeout_s=SAFETY_TIMEOUT_S)
            wait_until_healthy(url, server, timeout_s=SAFETY_TIMEOUT_S)
            listed = subprocess.run(
                [str(vlp), "rooms", "list", "--json", "--url", url, "--key", TERMINAL["X-API-Key"]],
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            assert listed.returncode == 0, listed.stderr
            assert json.loads(listed.stdout)[0]["name"] == "Paper room"
            demo_room_id = json.loads(listed.stdout)[0]["id"]
            denied = subprocess.run(
                [str(vlp), "rooms", "list", "--json", "--url", url],
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
                env={k: v for k, v in os.environ.items() if k not in _KEY_VARIABLES},
            )
            assert denied.returncode == 1 and json.loads(denied.stdout)["status"] == 401
        finally:
            server.terminate()
            server.wait(timeout=15)
    lines = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    assert any(line["message"].startswith(f"Uvicorn running on {url} ") for line in lines)
    access = [line for line in lines if line["logger"] == "app.access"]
    assert any(line["route"] == "/v1/rooms" and line["status"] == 200 for line in access)
    assert all(len(line["request_id"]) == 32 for line in access)
    # Start-up names the docs URL and the demo room; uvicorn's ANSI duplicate is dropped.
    started = next(line for line in lines if line["message"].startswith("service started"))
    assert started["docs_url"] == f"{url}/docs" and started["demo_room_id"] == demo_room_id
    assert f"{url}/docs" in started["message"] and demo_room_id in started["message"]
    assert not any("color_message" in line for line in lines)
    assert not any("\x1b[" in json.dumps(line) for line in lines)
