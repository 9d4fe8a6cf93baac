"""API keys and roles: 401 without or with an unknown key, 403 for the wrong role."""

from __future__ import annotations

import stat
from pathlib import Path
from typing import Any

import pytest

from app.api.security import CREDENTIALS_FILE, hash_key
from app.main import create_app

from .conftest import ADMIN, TERMINAL, TestClient, make_settings
from .test_rooms import assert_problem, small_room

# (method, path template, body) of every endpoint that needs a key.
_ADMIN_ONLY = [
    ("POST", "/v1/rooms", "layout"),
    ("PUT", "/v1/rooms/{room_id}", "layout"),
    ("DELETE", "/v1/rooms/{room_id}", None),
    ("POST", "/v1/rooms/{room_id}/fingerprints", None),
]
_ANY_ROLE = [
    ("GET", "/v1/rooms", None),
    ("GET", "/v1/rooms/{room_id}", None),
    ("GET", "/v1/rooms/{room_id}/fingerprints", None),
    ("GET", "/v1/rooms/{room_id}/fingerprints/current", None),
    ("GET", "/v1/rooms/{room_id}/fingerprints/current/H.npy", None),
    ("GET", "/v1/jobs/{job_id}", None),
    ("POST", "/v1/rooms/{room_id}/localize", "measurement"),
    ("POST", "/v1/rooms/{room_id}/simulate", "simulation"),
]
_BODIES: dict[str, dict[str, Any]] = {
    "layout": small_room(),
    "measurement": {"power": [1.0, 2.0]},
    "simulation": {"targets": 1},
}


def _call(
    client: TestClient,
    method: str,
    template: str,
    body: str | None,
    headers: dict[str, str],
    room: dict[str, Any],
) -> Any:
    path = template.format(room_id=room["id"], job_id=room["fingerprint"]["job_id"])
    extra = {"If-Match": '"stale"'} if method == "PUT" else {}
    return client.request(
        method, path, json=_BODIES[body] if body else None, headers={**headers, **extra}
    )


@pytest.fixture
def room(client: TestClient) -> dict[str, Any]:
    created: dict[str, Any] = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    return created


@pytest.mark.parametrize(
    "method, template, body",
    _ADMIN_ONLY + _ANY_ROLE,
    ids=lambda value: value if isinstance(value, str) else None,
)
@pytest.mark.parametrize(
    "headers",
    [{}, {"X-API-Key": "wrong"}, {"X-API-Key": ""}],
    ids=["no-key", "unknown-key", "empty-key"],
)
def test_missing_or_unknown_key_is_401(
    client: TestClient,
    room: dict[str, Any],
    method: str,
    template: str,
    body: str | None,
    headers: dict[str, str],
) -> None:
    assert_problem(_call(client, method, template, body, headers, room), 401)


@pytest.mark.parametrize(
    "method, template, body",
    _ADMIN_ONLY,
    ids=lambda value: value if isinstance(value, str) else None,
)
def test_terminal_may_not_write(
    client: TestClient, room: dict[str, Any], method: str, template: str, body: str | None
) -> None:
    assert_problem(_call(client, method, template, body, TERMINAL, room), 403)
    assert client.get(f"/v1/rooms/{room['id']}", headers=ADMIN).json() == room


@pytest.mark.parametrize(
    "method, template, body", _ANY_ROLE, ids=lambda value: value if isinstance(value, str) else None
)
@pytest.mark.parametrize("headers", [ADMIN, TERMINAL], ids=["admin", "terminal"])
def test_both_roles_pass_auth_on_read_and_localize(
    client: TestClient,
    room: dict[str, Any],
    method: str,
    template: str,
    body: str | None,
    headers: dict[str, str],
) -> None:
    response = _call(client, method, template, body, headers, room)
    # Past auth: 200, or 409 because this app builds no fingerprints.
    assert response.status_code in (200, 409), response.text
    if response.status_code == 409:
        assert "fingerprint" in template or method == "POST"


def test_admin_may_write(client: TestClient, room: dict[str, Any]) -> None:
    assert (
        _call(client, "POST", "/v1/rooms/{room_id}/fingerprints", None, ADMIN, room).status_code
        == 202
    )
    put = client.put(
        f"/v1/rooms/{room['id']}",
        json=small_room("New"),
        headers={**ADMIN, "If-Match": f'"{room["id"]}-1"'},
    )
    assert put.status_code == 200
    assert client.delete(f"/v1/rooms/{room['id']}", headers=ADMIN).status_code == 204


@pytest.mark.parametrize(
    "path", ["/healthz", "/readyz", "/metrics", "/docs", "/redoc", "/openapi.json"]
)
def test_open_endpoints_need_no_key(client: TestClient, path: str) -> None:
    assert client.get(path).status_code == 200


def _credentials(path: Path) -> dict[str, str]:
    lines = path.read_text(encoding="utf-8").splitlines()
    return dict(line.split("=", 1) for line in lines if line and not line.startswith("#"))


def test_first_start_generates_keys_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    settings = make_settings(tmp_path, admin_keys="", terminal_keys="")
    with (
        caplog.at_level("WARNING", logger="app.security"),
        TestClient(create_app(settings)) as client,
    ):
        path = tmp_path / CREDENTIALS_FILE
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        keys = _credentials(path)
        admin, terminal = keys["VLP_ADMIN_KEYS"], keys["VLP_TERMINAL_KEYS"]
        assert len(admin) >= 40 and len(terminal) >= 40 and admin != terminal
        assert admin in caplog.text and "printed once" in caplog.text
        assert (
            client.post("/v1/rooms", json=small_room(), headers={"X-API-Key": admin}).status_code
            == 201
        )
        assert (
            client.post("/v1/rooms", json=small_room(), headers={"X-API-Key": terminal}).status_code
            == 403
        )
        assert client.get("/v1/rooms", headers={"X-API-Key": terminal}).status_code == 200
    # Only hashes are stored in the registry database.
    database = (tmp_path / "registry.sqlite3").read_bytes()
    assert admin.encode() not in database and terminal.encode() not in database
    assert hash_key(admin).encode() in database or _wal_has(tmp_path, hash_key(admin))

    # A second start reuses the stored hashes and generates nothing new.
    caplog.clear()
    path.unlink()
    with (
        caplog.at_level("WARNING", logger="app.security"),
        TestClient(create_app(settings)) as client,
    ):
        assert not path.exists() and "printed once" not in caplog.text
        assert client.get("/v1/rooms", headers={"X-API-Key": admin}).status_code == 200


def _wal_has(data_dir: Path, text: str) -> bool:
    wal = data_dir / "registry.sqlite3-wal"
    return wal.exists() and text.encode() in wal.read_bytes()


def test_configured_keys_are_stored_as_hashes(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, admin_keys=" a-key , b-key ", terminal_keys="t-key")
    with TestClient(create_app(settings)) as client:
        for key in ("a-key", "b-key"):
            assert (
                client.post("/v1/rooms", json=small_room(), headers={"X-API-Key": key}).status_code
                == 201
            )
        assert client.get("/v1/rooms", headers={"X-API-Key": "t-key"}).status_code == 200
        assert not (tmp_path / CREDENTIALS_FILE).exists()
