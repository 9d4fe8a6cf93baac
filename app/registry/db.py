"""Engines, transactions and migrations for SQLite and PostgreSQL.

SQLite: WAL journal, a 30 s busy timeout and foreign keys on every connection; write
transactions start with ``BEGIN IMMEDIATE`` so two writers never deadlock on a lock upgrade
and a claim is atomic. PostgreSQL (``postgresql+psycopg``): pre-pinged pooled connections;
claims use ``SELECT ... FOR UPDATE SKIP LOCKED`` and migrations an advisory lock.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, create_engine, event, make_url, text
from sqlalchemy.engine import URL
from sqlalchemy.exc import DBAPIError, OperationalError

from .errors import RegistryUnavailable

__all__ = [
    "alembic_config",
    "create_registry_engine",
    "migrate",
    "migrations_current",
    "translate_errors",
    "write_transaction",
]

_MIGRATIONS = Path(__file__).resolve().parent / "migrations"
_SQLITE_BUSY_MS = 30_000
_MIGRATION_LOCK_KEY = 0x564C505F4D494752  # "VLP_MIGR"


def _normalise_url(database_url: str) -> URL:
    url = make_url(database_url)
    if url.drivername in ("postgresql", "postgres"):
        url = url.set(drivername="postgresql+psycopg")
    return url


def create_registry_engine(database_url: str) -> Engine:
    """An engine for ``database_url`` with the per-backend settings described above."""
    url = _normalise_url(database_url)
    if url.get_backend_name() != "sqlite":
        return create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=10)
    if url.database and url.database != ":memory:":
        Path(url.database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(
        url, connect_args={"timeout": _SQLITE_BUSY_MS / 1000, "check_same_thread": False}
    )

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, connection_record: Any) -> None:
        del connection_record
        dbapi_connection.isolation_level = None  # we emit BEGIN ourselves (below)
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA busy_timeout={_SQLITE_BUSY_MS}")
        _enable_wal(cursor)
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        immediate = conn.get_execution_options().get("sqlite_immediate", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")

    return engine


def _enable_wal(cursor: Any) -> None:
    """Switch to WAL; the switch needs a moment alone, which the busy handler does not wait for
    when a new file is opened by several connections at once, so retry briefly."""
    for attempt in range(50):
        try:
            if str(cursor.execute("PRAGMA journal_mode").fetchone()[0]).lower() == "wal":
                return
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError:
            if attempt == 49:
                raise
            time.sleep(0.02 * (1 + attempt % 5))


@contextmanager
def translate_errors() -> Iterator[None]:
    """Turn connection-level database errors into :class:`RegistryUnavailable`."""
    try:
        yield
    except OperationalError as exc:
        raise RegistryUnavailable(
            "the registry database is unavailable or busy; try again"
        ) from exc
    except DBAPIError as exc:
        if exc.connection_invalidated:
            raise RegistryUnavailable("the registry database connection was lost") from exc
        raise


@contextmanager
def write_transaction(engine: Engine) -> Iterator[Connection]:
    """A read-write transaction (``BEGIN IMMEDIATE`` on SQLite), committed on success."""
    with translate_errors(), engine.execution_options(sqlite_immediate=True).begin() as conn:
        yield conn


def alembic_config() -> Config:
    """The Alembic configuration of the packaged migrations (no ini file needed)."""
    config = Config()
    config.set_main_option("script_location", str(_MIGRATIONS))
    return config


def migrate(engine: Engine) -> None:
    """Upgrade to the newest revision; idempotent and safe when several processes race."""
    config = alembic_config()
    with write_transaction(engine) as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _MIGRATION_LOCK_KEY})
        config.attributes["connection"] = conn
        command.upgrade(config, "head")


def migrations_current(engine: Engine) -> bool:
    """True when the database is at the newest revision."""
    heads = set(ScriptDirectory.from_config(alembic_config()).get_heads())
    with translate_errors(), engine.connect() as conn:
        current = set(MigrationContext.configure(conn).get_current_heads())
    return current == heads
