"""Alembic environment (online only).

The registry hands over its connection (``Registry.migrate``); the ``alembic`` command line
(``alembic -c app/registry/alembic.ini revision --autogenerate -m ...``) connects to the URL
the service settings resolve (``VLP_DATABASE_URL`` or the SQLite file in ``VLP_DATA_DIR``).
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import Connection

from app.registry._schema import metadata
from app.registry.db import create_registry_engine
from app.settings import Settings


def _run(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=metadata,
        render_as_batch=connection.dialect.name == "sqlite",
    )
    with context.begin_transaction():
        context.run_migrations()


given = context.config.attributes.get("connection")
if isinstance(given, Connection):
    _run(given)
else:
    engine = create_registry_engine(Settings().resolved_database_url())
    try:
        with engine.begin() as conn:
            _run(conn)
    finally:
        engine.dispose()
