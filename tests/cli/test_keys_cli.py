"""``vlp keys create|list|revoke`` against a live ``vlp serve``."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from app.cli import EXIT_REFUSED, main
from tests.live_server import ADMIN_KEY, LiveServer, live_server

pytestmark = pytest.mark.slow

_KEY_VARIABLES = ("VLP_API_KEY", "VLP_ADMIN_KEYS", "VLP_TERMINAL_KEYS", "VLP_URL")


@pytest.fixture(autouse=True)
def _no_ambient_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    for variable in _KEY_VARIABLES:
        monkeypatch.delenv(variable, raising=False)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    with live_server(
        tmp_path_factory.mktemp("keys"), VLP_DEMO="0", VLP_EMBEDDED_WORKERS="0"
    ) as live:
        yield live


def _run(
    capsys: pytest.CaptureFixture[str], server: LiveServer, *argv: str, key: str = ADMIN_KEY
) -> tuple[int, str, str]:
    # --key=VALUE: an operator's key may start with "-", which "--key VALUE" reads as an option.
    code = main([*argv, "--url", server.url, f"--key={key}"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_keys_create_list_revoke(server: LiveServer, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(
        capsys, server, "keys", "create", "--role", "terminal", "--label", "kiosk", "--json"
    )
    assert code == 0, err
    created: dict[str, Any] = json.loads(out)
    secret = created["key"]
    assert created["role"] == "terminal" and len(secret) >= 40

    code, out, err = _run(capsys, server, "keys", "list")
    assert code == 0, err
    assert created["id"] in out and "kiosk" in out and secret not in out
    code, out, _ = _run(capsys, server, "keys", "list", "--json")
    assert secret not in out
    assert {item["source"] for item in json.loads(out)["items"]} == {"environment", "api"}

    assert _run(capsys, server, "rooms", "list", "--json", key=secret)[0] == 0
    code, out, err = _run(capsys, server, "keys", "revoke", created["id"])
    assert code == 0 and f"revoked {created['id']}" in out, err
    code, out, _ = _run(capsys, server, "rooms", "list", "--json", key=secret)
    assert code == EXIT_REFUSED and json.loads(out)["status"] == 401


def test_keys_create_prints_the_secret_once_for_people(
    server: LiveServer, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = _run(capsys, server, "keys", "create", "--role", "admin", "--label", "ops")
    assert code == 0, err
    secret = out.strip().splitlines()[-1]
    assert len(secret) >= 40 and " " not in secret
    assert _run(capsys, server, "keys", "list", "--json", key=secret)[0] == 0


def test_keys_need_an_admin(server: LiveServer, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, server, "keys", "list", "--json", key="not-a-key-" + "x" * 20)
    assert code == EXIT_REFUSED and json.loads(out)["status"] == 401
