"""API keys as a resource: an id, where each key came from, when it was last used or revoked.

Revision ID: 0004
Revises: 0003

Rows from before this migration cannot tell a generated key from an environment one; they
become ``generated``: they stay in force while no operator keys are configured, and the
next start with ``VLP_ADMIN_KEYS`` / ``VLP_TERMINAL_KEYS`` set re-marks the configured ones
``environment`` and drops the rest (see :mod:`app.registry.keys`).
"""

from __future__ import annotations

import uuid

import sqlalchemy as sa
from alembic import op

from app.registry._schema import UTCDateTime

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add ``id``, ``source``, ``last_used_at`` and ``revoked_at`` to ``api_keys``."""
    with op.batch_alter_table("api_keys") as batch:
        batch.add_column(sa.Column("id", sa.String(32), nullable=True))
        batch.add_column(
            sa.Column("source", sa.String(16), nullable=False, server_default="generated")
        )
        batch.add_column(sa.Column("last_used_at", UTCDateTime(), nullable=True))
        batch.add_column(sa.Column("revoked_at", UTCDateTime(), nullable=True))
    keys = sa.table("api_keys", sa.column("key_hash", sa.String), sa.column("id", sa.String))
    connection = op.get_bind()
    for (key_hash,) in connection.execute(sa.select(keys.c.key_hash)).all():
        connection.execute(
            sa.update(keys).where(keys.c.key_hash == key_hash).values(id=uuid.uuid4().hex)
        )
    with op.batch_alter_table("api_keys") as batch:
        batch.alter_column("id", existing_type=sa.String(32), nullable=False)
        batch.create_unique_constraint("uq_api_keys_id", ["id"])


def downgrade() -> None:
    """Drop what :func:`upgrade` added (revoked keys become valid again: delete them first)."""
    keys = sa.table("api_keys", sa.column("revoked_at", UTCDateTime()))
    op.get_bind().execute(sa.delete(keys).where(keys.c.revoked_at.is_not(None)))
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_constraint("uq_api_keys_id", type_="unique")
        batch.drop_column("revoked_at")
        batch.drop_column("last_used_at")
        batch.drop_column("source")
        batch.drop_column("id")
