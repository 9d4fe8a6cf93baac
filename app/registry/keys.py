"""API keys: stored by sha256 hash, with a role, a label, a source and a revocation time.

Sources and how long a key is in force:

- ``api``: made through ``POST /v1/keys``; in force until revoked.
- ``environment``: set in ``VLP_ADMIN_KEYS`` / ``VLP_TERMINAL_KEYS``. Each API start makes
  the stored environment keys equal to its own environment (:func:`sync_environment_keys`):
  rows of keys no longer set are deleted, so a key is in force only while it is set.
- ``generated``: the pair made at a start with no keys at all; in force only while no
  environment keys are configured (a start with some deletes them).

A revoked key keeps its row (``revoked_at`` set) so the same secret set again in the
environment stays refused; every lookup skips revoked rows.
"""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import Engine, and_, delete, func, insert, select, text, update

from app.clock import SystemClock

from ._schema import api_keys
from .db import translate_errors, write_transaction
from .errors import RecordNotFound, StateConflict
from .records import KeyRecord, KeySource

__all__ = [
    "add_generated_keys_if_no_admin",
    "count_active_admin_keys",
    "create_api_key",
    "get_active_key",
    "list_api_keys",
    "revoke_api_key",
    "sync_environment_keys",
    "touch_api_key",
]

# Rows stamped here (key use, blob upload) are records, not timing logic: real time.
_SYSTEM_CLOCK = SystemClock()

_KEYS_LOCK = 0x564C505F4B455953  # "VLP_KEYS": one start at a time syncs the environment keys


def _record(row: object) -> KeyRecord:
    mapping = row._mapping  # type: ignore[attr-defined]
    return KeyRecord(
        id=mapping["id"],
        key_hash=mapping["key_hash"],
        role=mapping["role"],
        label=mapping["label"],
        source=mapping["source"],
        created_at=mapping["created_at"],
        last_used_at=mapping["last_used_at"],
    )


_active = api_keys.c.revoked_at.is_(None)


def create_api_key(
    engine: Engine, *, key_hash: str, role: str, label: str, source: KeySource
) -> KeyRecord:
    """Store a new key by its hash (a hash already stored raises :class:`StateConflict`)."""
    key_id = uuid.uuid4().hex
    with write_transaction(engine) as conn:
        known = conn.execute(
            select(api_keys.c.id).where(api_keys.c.key_hash == key_hash)
        ).one_or_none()
        if known is not None:
            raise StateConflict("this key is already stored", field="key")
        conn.execute(
            insert(api_keys).values(
                key_hash=key_hash,
                id=key_id,
                role=role,
                label=label,
                source=source,
                created_at=_SYSTEM_CLOCK.now(),
            )
        )
        row = conn.execute(select(api_keys).where(api_keys.c.id == key_id)).one()
    return _record(row)


def list_api_keys(engine: Engine) -> list[KeyRecord]:
    """The keys in force, oldest first."""
    with translate_errors(), engine.connect() as conn:
        rows = conn.execute(
            select(api_keys).where(_active).order_by(api_keys.c.created_at, api_keys.c.id)
        ).all()
    return [_record(row) for row in rows]


def get_active_key(engine: Engine, *, key_hash: str) -> KeyRecord | None:
    """The key in force with this hash, or None (unknown or revoked)."""
    with translate_errors(), engine.connect() as conn:
        row = conn.execute(
            select(api_keys).where(and_(api_keys.c.key_hash == key_hash, _active))
        ).one_or_none()
    return None if row is None else _record(row)


def revoke_api_key(engine: Engine, *, key_id: str) -> KeyRecord:
    """Revoke a key in force.

    Raises
    ------
    RecordNotFound
        When no key in force has this id (``field="key_id"``).
    StateConflict
        When it is the last admin key in force: revoking it would lock every admin out.
    """
    with write_transaction(engine) as conn:
        row = conn.execute(
            select(api_keys).where(and_(api_keys.c.id == key_id, _active))
        ).one_or_none()
        if row is None:
            raise RecordNotFound(f"no key {key_id} in force", field="key_id")
        record = _record(row)
        if record.role == "admin":
            admins = conn.execute(
                select(func.count())
                .select_from(api_keys)
                .where(and_(api_keys.c.role == "admin", _active))
            ).scalar_one()
            if admins <= 1:
                raise StateConflict(
                    f"key {key_id} is the last admin key in force; create another admin key "
                    "before revoking it",
                    field="key_id",
                )
        conn.execute(
            update(api_keys).where(api_keys.c.id == key_id).values(revoked_at=_SYSTEM_CLOCK.now())
        )
    return record


def touch_api_key(engine: Engine, *, key_hash: str, when: datetime) -> None:
    """Record that a key was used at ``when`` (callers throttle how often)."""
    with write_transaction(engine) as conn:
        conn.execute(
            update(api_keys).where(api_keys.c.key_hash == key_hash).values(last_used_at=when)
        )


def sync_environment_keys(
    engine: Engine, *, configured: list[tuple[str, str]]
) -> tuple[list[str], list[str]]:
    """Make the stored environment keys those of ``configured`` ``(key_hash, role)`` pairs.

    Keys of the pairs are stored as ``environment`` keys (a key made through the API is
    re-marked; a generated key set in the environment, e.g. from a shell that sourced the
    credentials file, stays ``generated``). Environment keys not among them are deleted,
    and so are generated keys not among them when ``configured`` is not empty. Revoked keys
    stay revoked. Concurrent starts are serialised (an advisory lock on PostgreSQL).

    Returns
    -------
    revoked_ids : list of str
        Ids of configured keys that were revoked earlier (still refused).
    deleted_sources : list of str
        The source of each deleted row.
    """
    hashes = [key_hash for key_hash, _ in configured]
    now = _SYSTEM_CLOCK.now()
    revoked: list[str] = []
    with write_transaction(engine) as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _KEYS_LOCK})
        for key_hash, role in configured:
            row = conn.execute(
                select(api_keys).where(api_keys.c.key_hash == key_hash)
            ).one_or_none()
            if row is None:
                conn.execute(
                    insert(api_keys).values(
                        key_hash=key_hash,
                        id=uuid.uuid4().hex,
                        role=role,
                        label=f"{role} key from the environment",
                        source="environment",
                        created_at=now,
                    )
                )
            elif row._mapping["revoked_at"] is not None:
                revoked.append(str(row._mapping["id"]))
            elif row._mapping["source"] != "generated":
                conn.execute(
                    update(api_keys)
                    .where(api_keys.c.key_hash == key_hash)
                    .values(source="environment", role=role)
                )
        stale = api_keys.c.source == "environment"
        if configured:
            stale = stale | (api_keys.c.source == "generated")
        doomed = and_(stale, _active, api_keys.c.key_hash.not_in(hashes))
        sources = [
            str(source)
            for source in conn.execute(select(api_keys.c.source).where(doomed)).scalars()
        ]
        conn.execute(delete(api_keys).where(doomed))
    return revoked, sources


def add_generated_keys_if_no_admin(engine: Engine, *, keys: list[tuple[str, str]]) -> bool:
    """Store ``(key_hash, role)`` pairs as ``generated`` keys if no admin key is in force.

    Returns whether they were stored; serialised like :func:`sync_environment_keys`, so of
    several processes starting at once on an empty registry only one generates keys.
    """
    now = _SYSTEM_CLOCK.now()
    with write_transaction(engine) as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _KEYS_LOCK})
        admins = conn.execute(
            select(func.count())
            .select_from(api_keys)
            .where(and_(api_keys.c.role == "admin", _active))
        ).scalar_one()
        if admins:
            return False
        for key_hash, role in keys:
            conn.execute(
                insert(api_keys).values(
                    key_hash=key_hash,
                    id=uuid.uuid4().hex,
                    role=role,
                    label=f"{role} key generated at start",
                    source="generated",
                    created_at=now,
                )
            )
    return True


def count_active_admin_keys(engine: Engine) -> int:
    """How many admin keys are in force."""
    with translate_errors(), engine.connect() as conn:
        return int(
            conn.execute(
                select(func.count())
                .select_from(api_keys)
                .where(and_(api_keys.c.role == "admin", _active))
            ).scalar_one()
        )
