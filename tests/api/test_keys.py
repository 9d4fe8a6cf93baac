"""API keys as a resource: create, list, revoke; the start-up rules; the per-process cache."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import httpx
import pytest
from pydantic import ValidationError

from app.api.security import CREDENTIALS_FILE, KEY_CACHE_TTL_S, KeyCache, hash_key
from app.main import create_app
from app.registry import Registry
from app.registry.records import KeyRecord
from tests.live_server import ADMIN_KEY as LIVE_ADMIN_KEY
from tests.live_server import live_server
from tests.waiting import wait_for

from .conftest import ADMIN, ADMIN_KEY, TERMINAL, TestClient, assert_problem, make_settings

ROOMS = "/v1/rooms"


def _key(client: TestClient, role: str, label: str = "a label") -> dict[str, str]:
    answer = client.post("/v1/keys", json={"role": role, "label": label}, headers=ADMIN)
    assert answer.status_code == 201, answer.text
    created: dict[str, str] = answer.json()
    return created


def test_create_list_revoke(client: TestClient) -> None:
    created = _key(client, "terminal", "lobby kiosk")
    assert created["role"] == "terminal" and created["label"] == "lobby kiosk"
    secret = {"X-API-Key": created["key"]}
    assert len(created["key"]) >= 40
    assert client.get(ROOMS, headers=secret).status_code == 200
    assert_problem(client.post(ROOMS, json={}, headers=secret), 403)

    listed = client.get("/v1/keys", headers=ADMIN)
    assert listed.status_code == 200
    assert created["key"] not in listed.text and ADMIN_KEY not in listed.text
    by_id = {item["id"]: item for item in listed.json()["items"]}
    assert by_id[created["id"]]["source"] == "api"
    # The key was just used, so its last use is recorded (the first use always is).
    assert by_id[created["id"]]["last_used_at"] is not None
    assert {item["source"] for item in by_id.values()} == {"api", "environment"}

    assert client.delete(f"/v1/keys/{created['id']}", headers=ADMIN).status_code == 204
    problem = assert_problem(client.get(ROOMS, headers=secret), 401)
    assert "unknown API key" in problem["detail"]
    assert created["id"] not in client.get("/v1/keys", headers=ADMIN).text
    assert_problem(client.delete(f"/v1/keys/{created['id']}", headers=ADMIN), 404)


def test_keys_are_for_admins_only(client: TestClient) -> None:
    assert_problem(client.get("/v1/keys", headers=TERMINAL), 403)
    refused = client.post("/v1/keys", json={"role": "admin", "label": "x"}, headers=TERMINAL)
    assert_problem(refused, 403)


def test_bad_create_bodies_name_the_field(client: TestClient) -> None:
    problem = assert_problem(
        client.post("/v1/keys", json={"role": "root", "label": "x"}, headers=ADMIN), 422
    )
    assert problem["errors"][0]["field"] == "body.role", problem
    problem = assert_problem(
        client.post("/v1/keys", json={"role": "admin", "label": ""}, headers=ADMIN), 422
    )
    assert problem["errors"][0]["field"] == "body.label", problem


def test_the_last_admin_key_cannot_be_revoked(client: TestClient) -> None:
    admins = [
        k for k in client.get("/v1/keys", headers=ADMIN).json()["items"] if k["role"] == "admin"
    ]
    assert len(admins) == 1
    problem = assert_problem(client.delete(f"/v1/keys/{admins[0]['id']}", headers=ADMIN), 409)
    assert "last admin key" in problem["detail"]
    second = _key(client, "admin")
    assert client.delete(f"/v1/keys/{admins[0]['id']}", headers=ADMIN).status_code == 204
    assert_problem(client.get(ROOMS, headers=ADMIN), 401)
    assert client.get(ROOMS, headers={"X-API-Key": second["key"]}).status_code == 200


def test_environment_keys_end_when_unset_and_generated_keys_when_operator_keys_are_set(
    tmp_path: Path,
) -> None:
    with TestClient(create_app(make_settings(tmp_path))) as client:
        made = _key(client, "terminal")
    # A restart without the environment keys: they no longer work, keys made by the API do;
    # with no admin key in force a new pair is generated (and written to credentials).
    bare = make_settings(tmp_path, admin_keys="", terminal_keys="")
    with TestClient(create_app(bare)) as client:
        assert_problem(client.get(ROOMS, headers=ADMIN), 401)
        assert_problem(client.get(ROOMS, headers=TERMINAL), 401)
        assert client.get(ROOMS, headers={"X-API-Key": made["key"]}).status_code == 200
        generated = (tmp_path / CREDENTIALS_FILE).read_text(encoding="utf-8")
        admin_line = next(line for line in generated.splitlines() if "ADMIN_KEY=" in line)
        generated_admin = {"X-API-Key": admin_line.split("=", 1)[1]}
        assert client.get(ROOMS, headers=generated_admin).status_code == 200
    # The operator sets their own keys: the generated ones stop working, their file goes.
    with TestClient(create_app(make_settings(tmp_path))) as client:
        assert_problem(client.get(ROOMS, headers=generated_admin), 401)
        assert not (tmp_path / CREDENTIALS_FILE).exists()
        assert client.get(ROOMS, headers=ADMIN).status_code == 200
        sources = {k["source"] for k in client.get("/v1/keys", headers=ADMIN).json()["items"]}
        assert sources == {"environment", "api"}


@pytest.mark.parametrize("variable", ["admin_keys", "terminal_keys"])
def test_short_environment_keys_are_refused(tmp_path: Path, variable: str) -> None:
    with pytest.raises(
        ValidationError, match=r"at least 24 characters; got 1 shorter \(length 1\)"
    ):
        make_settings(tmp_path, **{variable: f"{'k' * 24},t"})
    assert make_settings(tmp_path, **{variable: "k" * 24}).admin_key_list()


class _FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class _CountingRegistry(Registry):
    """A real registry that counts key lookups and last-use writes."""

    lookups = 0
    touches = 0

    def get_active_key(self, *, key_hash: str) -> KeyRecord | None:
        self.lookups += 1
        return super().get_active_key(key_hash=key_hash)

    def touch_api_key(self, *, key_hash: str, when: datetime) -> None:
        self.touches += 1
        super().touch_api_key(key_hash=key_hash, when=when)


def test_key_cache_answers_from_memory_until_its_ttl_passes(tmp_path: Path) -> None:
    registry = _CountingRegistry(
        database_url=f"sqlite:///{tmp_path / 'r.sqlite3'}", data_dir=tmp_path
    )
    registry.migrate()
    try:
        for key, role in (("admin-" + "a" * 24, "admin"), ("other-" + "o" * 24, "admin")):
            registry.create_api_key(key_hash=hash_key(key), role=role, label="x", source="api")
        clock = _FakeClock()
        cache = KeyCache(registry=registry, ttl_s=1.0, touch_interval_s=60.0, clock=clock)
        key = "admin-" + "a" * 24
        assert cache.role_for(key) == "admin"
        assert (registry.lookups, registry.touches) == (1, 1)
        clock.now += 0.9
        assert cache.role_for(key) == "admin"
        assert (registry.lookups, registry.touches) == (1, 1)  # no round-trip while fresh
        # Revoked in the registry (as another process would): still cached, until 1 s passed.
        registry.revoke_api_key(key_id=registry.get_active_key(key_hash=hash_key(key)).id)  # type: ignore[union-attr]
        lookups = registry.lookups
        assert cache.role_for(key) == "admin"
        clock.now += 0.1
        assert cache.role_for(key) is None
        assert registry.lookups == lookups + 1
        # Unknown keys are never cached: each asks the registry.
        assert cache.role_for("nobody-" + "n" * 24) is None
        assert cache.role_for("nobody-" + "n" * 24) is None
        assert registry.lookups == lookups + 3
    finally:
        registry.dispose()


def test_fresh_role_answers_only_what_needs_no_registry_round_trip(tmp_path: Path) -> None:
    """``fresh_role`` (the event loop's check) answers from memory exactly when ``role_for``
    would: a key read within the TTL whose last use needs no write; else None (ask)."""
    registry = _CountingRegistry(
        database_url=f"sqlite:///{tmp_path / 'r.sqlite3'}", data_dir=tmp_path
    )
    registry.migrate()
    try:
        key = "terminal-" + "t" * 24
        registry.create_api_key(key_hash=hash_key(key), role="terminal", label="t", source="api")
        clock = _FakeClock()
        cache = KeyCache(registry=registry, ttl_s=1.0, touch_interval_s=5.0, clock=clock)
        assert cache.fresh_role(key) is None  # never read
        assert cache.role_for(key) == "terminal"
        clock.now += 0.9
        assert cache.fresh_role(key) == "terminal"
        assert cache.fresh_role("nobody-" + "n" * 24) is None
        clock.now += 0.1
        assert cache.fresh_role(key) is None  # the TTL passed: the registry must be asked
        assert cache.role_for(key) == "terminal"
        clock.now += 3.5  # now 4.5 s: read again, fresh until 5.5 s; last use written at 0
        assert cache.role_for(key) == "terminal"
        clock.now += 0.7
        assert cache.fresh_role(key) is None  # read 0.7 s ago, but last_used_at is due
        assert (registry.lookups, registry.touches) == (3, 1)
        assert cache.role_for(key) == "terminal"  # writes it
        assert cache.fresh_role(key) == "terminal"
        assert (registry.lookups, registry.touches) == (3, 2)
    finally:
        registry.dispose()


def test_key_cache_writes_last_use_at_most_once_per_interval(tmp_path: Path) -> None:
    registry = _CountingRegistry(
        database_url=f"sqlite:///{tmp_path / 'r.sqlite3'}", data_dir=tmp_path
    )
    registry.migrate()
    try:
        key = "terminal-" + "t" * 24
        registry.create_api_key(key_hash=hash_key(key), role="terminal", label="t", source="api")
        clock = _FakeClock()
        cache = KeyCache(registry=registry, ttl_s=1.0, touch_interval_s=60.0, clock=clock)
        for _ in range(50):
            assert cache.role_for(key) == "terminal"
            clock.now += 1.0
        # 50 uses over 50 s: one write; the next after 60 s.
        assert registry.touches == 1
        clock.now += 10.0
        assert cache.role_for(key) == "terminal"
        assert registry.touches == 2
    finally:
        registry.dispose()


def test_a_key_revoked_through_one_process_is_refused_by_another(tmp_path: Path) -> None:
    """Two apps on one registry: a revocation made through the first reaches the second."""
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings)) as first, TestClient(create_app(settings)) as second:
        made = _key(first, "terminal")
        secret = {"X-API-Key": made["key"]}
        assert second.get(ROOMS, headers=secret).status_code == 200  # now cached in `second`
        assert first.delete(f"/v1/keys/{made['id']}", headers=ADMIN).status_code == 204
        assert_problem(first.get(ROOMS, headers=secret), 401)
        # The second refuses it once its cache entry (KEY_CACHE_TTL_S) expired.
        wait_for(
            lambda: second.get(ROOMS, headers=secret).status_code == 401,
            "the second app to refuse the revoked key",
            poll_s=KEY_CACHE_TTL_S / 10,
        )


def test_a_credentials_file_of_the_first_format_is_rewritten_with_exports(tmp_path: Path) -> None:
    """Files written before the keys resource had plain `VLP_*_KEYS=` lines: not exported."""
    bare = make_settings(tmp_path, admin_keys="", terminal_keys="")
    with TestClient(create_app(bare)):
        pass
    path = tmp_path / CREDENTIALS_FILE
    exported = dict(
        line.removeprefix("export ").split("=", 1)
        for line in path.read_text(encoding="utf-8").splitlines()
        if line.startswith("export ADMIN_KEY=") or line.startswith("export TERMINAL_KEY=")
    )
    old_format = (
        "# VLP API keys generated at first start; only their hashes are stored.\n"
        f"VLP_ADMIN_KEYS={exported['ADMIN_KEY']}\nVLP_TERMINAL_KEYS={exported['TERMINAL_KEY']}\n"
    )
    path.write_text(old_format, encoding="utf-8")
    with TestClient(create_app(bare)) as client:
        text = path.read_text(encoding="utf-8")
        assert f"export ADMIN_KEY={exported['ADMIN_KEY']}\n" in text
        assert f"export TERMINAL_KEY={exported['TERMINAL_KEY']}\n" in text
        headers = {"X-API-Key": exported["ADMIN_KEY"]}
        assert client.get(ROOMS, headers=headers).status_code == 200
    # A file naming keys no longer in force is left alone.
    stale = old_format.replace(exported["ADMIN_KEY"], "z" * 43)
    path.write_text(stale, encoding="utf-8")
    with TestClient(create_app(bare)):
        assert path.read_text(encoding="utf-8") == stale


@pytest.mark.slow
def test_two_real_api_processes_on_postgresql_see_a_revocation(
    tmp_path: Path, postgres_url: str
) -> None:
    """Two `vlp serve` processes sharing only PostgreSQL: a key revoked through the first is
    refused by the second (which had it cached) once its cache entry expired."""
    with (
        live_server(tmp_path / "a", VLP_DATABASE_URL=postgres_url, VLP_DEMO="0") as first,
        live_server(tmp_path / "b", VLP_DATABASE_URL=postgres_url, VLP_DEMO="0") as second,
        httpx.Client(base_url=first.url, timeout=30) as a,
        httpx.Client(base_url=second.url, timeout=30) as b,
    ):
        admin = {"X-API-Key": LIVE_ADMIN_KEY}
        made = a.post("/v1/keys", json={"role": "terminal", "label": "t"}, headers=admin).json()
        secret = {"X-API-Key": made["key"]}
        assert b.get(ROOMS, headers=secret).status_code == 200
        assert a.delete(f"/v1/keys/{made['id']}", headers=admin).status_code == 204
        assert a.get(ROOMS, headers=secret).status_code == 401
        wait_for(
            lambda: b.get(ROOMS, headers=secret).status_code == 401,
            "the second process to refuse the revoked key",
            poll_s=KEY_CACHE_TTL_S / 10,
        )
