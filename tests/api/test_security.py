"""API keys and roles: 401 without or with an unknown key, 403 for the wrong role."""

from __future__ import annotations

import logging
import os
import select
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.api.security import CREDENTIALS_FILE, KEY_PREFIX, MIN_KEY_LENGTH, generate_key, hash_key
from app.main import create_app

from .conftest import ADMIN, TERMINAL, TestClient, assert_problem, make_settings, small_room

# Operations anyone may call without a key (openapi/openapi.json); every other one needs a key.
_OPEN = {("GET", "/healthz"), ("GET", "/readyz"), ("GET", "/metrics")}
_UNKNOWN_KEY = "vlp-unknown-key-5f1c0f7a9d"
# What may not appear in any answer: keys, stack traces, SQL, driver names.
_LEAKS = ("Traceback", 'File "', "SELECT ", "INSERT ", "UPDATE ", "sqlalchemy", "psycopg")


def _operations() -> list[tuple[str, str, dict[str, Any]]]:
    """(method, path, operation) of every operation the app documents, found at collection."""
    document = create_app(make_settings(Path("unused"))).openapi()
    return [
        (method.upper(), path, operation)
        for path, operations in document["paths"].items()
        for method, operation in operations.items()
    ]


_OPERATIONS = _operations()


def _role_needed(method: str, path: str, operation: dict[str, Any]) -> str:
    """`open`, `any` or `admin`, read from the document (the matrix then checks it).

    An operation that declares no key must be one of the known open ones: a new route that
    forgot its key dependency fails here. A documented 403 means admin only.
    """
    if not operation.get("security"):
        assert (method, path) in _OPEN, f"{method} {path} needs no key and is not known open"
        return "open"
    assert (method, path) not in _OPEN, f"{method} {path} should be open"
    return "admin" if "403" in operation["responses"] else "any"


def _path_value(name: str, parameter: dict[str, Any], room: dict[str, Any]) -> str:
    known = {"room_id": room["id"], "job_id": room["fingerprint"]["job_id"]}
    if name in known:
        return str(known[name])
    schema = parameter.get("schema", {})
    choices = schema.get("enum") or parameter.get("examples") or schema.get("examples")
    if isinstance(choices, dict):  # OpenAPI `examples`: {name: {"value": ...}}
        return str(next(iter(choices.values()))["value"])
    return str(choices[0]) if choices else "unknown-id"


def _request(
    client: TestClient,
    method: str,
    path: str,
    operation: dict[str, Any],
    room: dict[str, Any],
    key: str | None,
) -> Any:
    parameters = {p["name"]: p for p in operation.get("parameters", []) if p["in"] == "path"}
    url = path.format(**{name: _path_value(name, p, room) for name, p in parameters.items()})
    headers = {"X-API-Key": key} if key is not None else {}
    if method == "PUT":
        headers["If-Match"] = '"stale"'
    body: dict[str, Any] | None = {} if "requestBody" in operation else None
    if "text/event-stream" in operation["responses"].get("200", {}).get("content", {}):
        return _stream_head(client, method, url, headers)
    return client.request(method, url, json=body, headers=headers)


def _stream_head(client: TestClient, method: str, url: str, headers: dict[str, str]) -> Any:
    """An endless event stream's answer: its status and headers when it streams (the body
    never ends), else the whole refusal."""
    with client.stream(method, url, headers=headers) as response:
        if response.status_code == 200:
            return httpx.Response(200, headers=response.headers, request=response.request)
        response.read()
    return response


def _assert_no_leak(response: Any) -> None:
    text = response.text + " ".join(f"{k}: {v}" for k, v in response.headers.items())
    for secret in (ADMIN["X-API-Key"], TERMINAL["X-API-Key"], _UNKNOWN_KEY, *_LEAKS):
        assert secret not in text, (secret, response.request.url, text[:500])


@pytest.fixture
def room(client: TestClient) -> dict[str, Any]:
    created: dict[str, Any] = client.post("/v1/rooms", json=small_room(), headers=ADMIN).json()
    return created


def test_every_documented_operation_is_in_the_matrix() -> None:
    pairs = {(method, path) for method, path, _ in _OPERATIONS}
    assert pairs >= _OPEN
    assert {("POST", "/v1/rooms"), ("POST", "/v1/rooms/{room_id}/localize")} <= pairs


def test_a_route_that_forgot_its_key_is_not_classified() -> None:
    app = create_app(make_settings(Path("unused")))

    @app.get("/v1/forgotten")
    def forgotten() -> dict[str, str]:
        return {"secret": "data"}

    operation = app.openapi()["paths"]["/v1/forgotten"]["get"]
    with pytest.raises(AssertionError, match="needs no key and is not known open"):
        _role_needed("GET", "/v1/forgotten", operation)


@pytest.mark.parametrize(
    "method, path, operation", _OPERATIONS, ids=[f"{m} {p}" for m, p, _ in _OPERATIONS]
)
def test_role_matrix(
    client: TestClient,
    room: dict[str, Any],
    caplog: pytest.LogCaptureFixture,
    method: str,
    path: str,
    operation: dict[str, Any],
) -> None:
    """Every operation x (no key, unknown key, terminal, admin): 401, 401, 403 or through.

    The admin goes last: its request may change the room (a DELETE really deletes).
    """
    needed = _role_needed(method, path, operation)
    answers: dict[str, Any] = {}
    with caplog.at_level(logging.DEBUG):
        for name, key in (
            ("no key", None),
            ("empty key", ""),
            ("unknown key", _UNKNOWN_KEY),
            ("terminal", TERMINAL["X-API-Key"]),
        ):
            answers[name] = _request(client, method, path, operation, room, key)
        if needed != "open":
            after_terminal = client.get(f"/v1/rooms/{room['id']}", headers=ADMIN).json()
        answers["admin"] = _request(client, method, path, operation, room, ADMIN["X-API-Key"])
    for response in answers.values():
        _assert_no_leak(response)
        assert response.status_code < 500, response.text
    # Keys are never logged.
    for key in (ADMIN["X-API-Key"], TERMINAL["X-API-Key"], _UNKNOWN_KEY):
        assert key not in caplog.text
    if needed == "open":
        assert all(response.status_code == 200 for response in answers.values()), answers
        return
    for name in ("no key", "empty key", "unknown key"):
        problem = assert_problem(answers[name], 401)
        assert "API key" in problem["detail"], problem
        assert answers[name].headers["www-authenticate"] == "X-API-Key"
    if needed == "admin":
        assert_problem(answers["terminal"], 403)
        assert after_terminal == room  # the refused terminal changed nothing
    else:
        assert answers["terminal"].status_code not in (401, 403), answers["terminal"].text
    assert answers["admin"].status_code not in (401, 403), answers["admin"].text


def test_admin_may_write(client: TestClient, room: dict[str, Any]) -> None:
    path = f"/v1/rooms/{room['id']}"
    assert client.post(f"{path}/fingerprints", headers=ADMIN).status_code == 202
    put = client.put(
        path, json=small_room("New"), headers={**ADMIN, "If-Match": f'"{room["id"]}-1"'}
    )
    assert put.status_code == 200
    assert client.delete(path, headers=ADMIN).status_code == 204


@pytest.mark.parametrize(
    "path", ["/healthz", "/readyz", "/metrics", "/docs", "/redoc", "/openapi.json"]
)
def test_open_endpoints_need_no_key(client: TestClient, path: str) -> None:
    assert client.get(path).status_code == 200


def _credentials(path: Path) -> dict[str, str]:
    """The variables a shell has after ``source``-ing the credentials file (and only it)."""
    names = ("VLP_URL", "ADMIN_KEY", "TERMINAL_KEY", "VLP_ADMIN_KEYS", "VLP_TERMINAL_KEYS")
    script = 'set -eu; source "$1"; ' + "; ".join(f'echo "{n}=${{{n}}}"' for n in names)
    result = subprocess.run(
        ["bash", "-c", script, "bash", str(path)],
        env={"PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        check=True,
    )
    return dict(line.split("=", 1) for line in result.stdout.splitlines())


def test_first_start_generates_keys_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    settings = make_settings(
        tmp_path, admin_keys="", terminal_keys="", public_url="http://127.0.0.1:8123"
    )
    with caplog.at_level(logging.DEBUG), TestClient(create_app(settings)) as client:
        path = tmp_path / CREDENTIALS_FILE
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        keys = _credentials(path)
        admin, terminal = keys["ADMIN_KEY"], keys["TERMINAL_KEY"]
        assert keys["VLP_ADMIN_KEYS"] == admin and keys["VLP_TERMINAL_KEYS"] == terminal
        assert keys["VLP_URL"] == "http://127.0.0.1:8123"
        assert len(admin) >= 40 and len(terminal) >= 40 and admin != terminal
        # stderr is captured here, not a terminal: the keys stay in the file, and the
        # start-up line says where it is (the terminal case: the pseudo-terminal test below).
        printed = capsys.readouterr().err
        assert admin not in printed and terminal not in printed
        assert admin not in caplog.text and terminal not in caplog.text
        started = [r.getMessage() for r in caplog.records if "service started" in r.getMessage()]
        assert len(started) == 1 and f"generated API keys in {path}" in started[0]
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
    path.unlink()
    with TestClient(create_app(settings)) as client:
        assert not path.exists() and admin not in capsys.readouterr().err
        assert client.get("/v1/rooms", headers={"X-API-Key": admin}).status_code == 200


def test_generated_keys_are_printed_only_on_a_terminal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """With stderr a pseudo-terminal the generated keys are shown there once; never in a log."""
    settings = make_settings(tmp_path, admin_keys="", terminal_keys="")
    leader, follower = os.openpty()
    with os.fdopen(follower, "w", encoding="utf-8") as terminal_stderr:
        monkeypatch.setattr(sys, "stderr", terminal_stderr)
        with caplog.at_level(logging.DEBUG), TestClient(create_app(settings)):
            pass
    shown = _drain(leader)
    keys = _credentials(tmp_path / CREDENTIALS_FILE)
    text = shown.decode("utf-8")
    assert keys["ADMIN_KEY"] in text and keys["TERMINAL_KEY"] in text
    assert str(tmp_path / CREDENTIALS_FILE) in text
    assert keys["ADMIN_KEY"] not in caplog.text and keys["TERMINAL_KEY"] not in caplog.text


def _drain(leader: int) -> bytes:
    """What the terminal's side of a pseudo-terminal holds (its other side closed)."""
    shown = b""
    try:
        while select.select([leader], [], [], 0)[0]:
            chunk = os.read(leader, 65536)
            if not chunk:
                break
            shown += chunk
    except OSError:  # EIO: everything written was read and the other side is closed
        pass
    finally:
        os.close(leader)
    return shown


def _wal_has(data_dir: Path, text: str) -> bool:
    wal = data_dir / "registry.sqlite3-wal"
    return wal.exists() and text.encode() in wal.read_bytes()


def test_configured_keys_are_stored_as_hashes(tmp_path: Path) -> None:
    a_key, b_key, t_key = "a-key-0123456789abcdefghij", "b-key-0123456789abcdefghij", "t" * 24
    settings = make_settings(tmp_path, admin_keys=f" {a_key} , {b_key} ", terminal_keys=t_key)
    with TestClient(create_app(settings)) as client:
        for key in (a_key, b_key):
            assert (
                client.post("/v1/rooms", json=small_room(), headers={"X-API-Key": key}).status_code
                == 201
            )
        assert client.get("/v1/rooms", headers={"X-API-Key": t_key}).status_code == 200
        assert not (tmp_path / CREDENTIALS_FILE).exists()


def test_generated_keys_are_prefixed_and_never_read_as_a_command_line_option() -> None:
    # Bare URL-safe base64 starts with "-" one time in 64, which `vlp ... --key KEY` reads
    # as an option: every generated key starts with the prefix instead.
    keys = [generate_key() for _ in range(2000)]
    assert all(key.startswith(KEY_PREFIX) and len(key) >= MIN_KEY_LENGTH for key in keys)
    assert len(set(keys)) == len(keys)
    assert {len(key) for key in keys} == {len(KEY_PREFIX) + 43}
