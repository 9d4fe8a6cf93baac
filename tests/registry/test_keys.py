"""API keys in the registry: sources, the environment sync, revocation and the 0004 migration."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic import command

from app.registry import Registry
from app.registry.db import alembic_config, write_transaction
from app.registry.errors import RecordNotFound, StateConflict
from tests.db_fixtures import raw_engine


def _in_force(registry: Registry) -> dict[str, tuple[str, str]]:
    """key_hash -> (role, source) of every key in force."""
    return {key.key_hash: (key.role, key.source) for key in registry.list_api_keys()}


def test_environment_keys_are_in_force_only_while_configured(registry: Registry) -> None:
    registry.sync_environment_keys(configured=[("a" * 64, "admin"), ("t" * 64, "terminal")])
    assert _in_force(registry) == {
        "a" * 64: ("admin", "environment"),
        "t" * 64: ("terminal", "environment"),
    }
    _, deleted = registry.sync_environment_keys(configured=[("b" * 64, "admin")])
    assert sorted(deleted) == ["environment", "environment"]
    assert _in_force(registry) == {"b" * 64: ("admin", "environment")}
    assert registry.get_active_key(key_hash="a" * 64) is None
    registry.sync_environment_keys(configured=[])
    assert _in_force(registry) == {}


def test_generated_keys_end_when_operator_keys_are_set(registry: Registry) -> None:
    registry.create_api_key(key_hash="g" * 64, role="admin", label="g", source="generated")
    api_key = registry.create_api_key(key_hash="p" * 64, role="terminal", label="p", source="api")
    # No environment keys: generated keys stay.
    assert registry.sync_environment_keys(configured=[]) == ([], [])
    assert "g" * 64 in _in_force(registry)
    _, deleted = registry.sync_environment_keys(configured=[("e" * 64, "admin")])
    assert deleted == ["generated"]
    assert _in_force(registry) == {
        "p" * 64: ("terminal", "api"),
        "e" * 64: ("admin", "environment"),
    }
    # Keys made through the API outlive any environment.
    registry.sync_environment_keys(configured=[])
    assert [key.id for key in registry.list_api_keys()] == [api_key.id]


def test_a_revoked_key_stays_refused_when_configured_again(registry: Registry) -> None:
    registry.sync_environment_keys(configured=[("a" * 64, "admin"), ("b" * 64, "admin")])
    first = registry.get_active_key(key_hash="a" * 64)
    assert first is not None
    registry.revoke_api_key(key_id=first.id)
    assert registry.get_active_key(key_hash="a" * 64) is None
    revoked, _ = registry.sync_environment_keys(
        configured=[("a" * 64, "admin"), ("b" * 64, "admin")]
    )
    assert revoked == [first.id]
    assert registry.get_active_key(key_hash="a" * 64) is None
    with pytest.raises(RecordNotFound, match=first.id):
        registry.revoke_api_key(key_id=first.id)


def test_the_last_admin_key_cannot_be_revoked(registry: Registry) -> None:
    admin = registry.create_api_key(key_hash="a" * 64, role="admin", label="a", source="api")
    terminal = registry.create_api_key(key_hash="t" * 64, role="terminal", label="t", source="api")
    with pytest.raises(StateConflict, match="last admin key"):
        registry.revoke_api_key(key_id=admin.id)
    registry.revoke_api_key(key_id=terminal.id)
    assert registry.count_active_admin_keys() == 1
    with pytest.raises(StateConflict, match="already stored"):
        registry.create_api_key(key_hash="a" * 64, role="terminal", label="again", source="api")


def test_last_used_is_recorded(registry: Registry) -> None:
    key = registry.create_api_key(key_hash="a" * 64, role="admin", label="a", source="api")
    assert key.last_used_at is None
    when = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    registry.touch_api_key(key_hash="a" * 64, when=when)
    stored = registry.get_active_key(key_hash="a" * 64)
    assert stored is not None and stored.last_used_at == when


def test_migration_0004_keeps_older_keys_as_generated(database_url: str, tmp_path: Path) -> None:
    """Keys stored before 0004 get an id and the source `generated` (see the migration)."""
    registry = Registry(database_url=database_url, data_dir=tmp_path / "data")
    try:
        config = alembic_config()
        with write_transaction(raw_engine(registry)) as conn:
            config.attributes["connection"] = conn
            command.upgrade(config, "0003")
            conn.execute(
                sa.text(
                    "INSERT INTO api_keys (key_hash, role, label, created_at) "
                    "VALUES (:h1, 'admin', 'admin key', :now), (:h2, 'terminal', 't', :now)"
                ),
                {"h1": "1" * 64, "h2": "2" * 64, "now": datetime.now(UTC)},
            )
        registry.migrate()
        keys = registry.list_api_keys()
        assert {key.key_hash: key.source for key in keys} == {
            "1" * 64: "generated",
            "2" * 64: "generated",
        }
        assert len({key.id for key in keys}) == 2 and all(len(key.id) == 32 for key in keys)
    finally:
        registry.dispose()


def test_generated_keys_set_in_the_environment_stay_generated(registry: Registry) -> None:
    """A shell that sourced the credentials file and started the server keeps its keys."""
    registry.create_api_key(key_hash="g" * 64, role="admin", label="g", source="generated")
    registry.create_api_key(key_hash="h" * 64, role="terminal", label="h", source="generated")
    configured = [("g" * 64, "admin"), ("h" * 64, "terminal")]
    assert registry.sync_environment_keys(configured=configured) == ([], [])
    assert registry.sync_environment_keys(configured=[]) == ([], [])
    assert _in_force(registry) == {
        "g" * 64: ("admin", "generated"),
        "h" * 64: ("terminal", "generated"),
    }


def test_generated_keys_only_when_no_admin_key_is_in_force(registry: Registry) -> None:
    pair = [("g" * 64, "admin"), ("h" * 64, "terminal")]
    assert registry.add_generated_keys_if_no_admin(keys=pair)
    # A second process starting at the same time finds the admin key and stores nothing.
    assert not registry.add_generated_keys_if_no_admin(keys=[("x" * 64, "admin")])
    assert _in_force(registry) == {
        "g" * 64: ("admin", "generated"),
        "h" * 64: ("terminal", "generated"),
    }
