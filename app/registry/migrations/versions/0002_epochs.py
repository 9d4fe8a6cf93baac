"""Cooperation epochs: the window of each epoch and the amplitudes its terminals posted.

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from app.registry._schema import UTCDateTime

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Create ``epochs`` and ``epoch_measurements`` (one row per (epoch, terminal))."""
    op.create_table(
        "epochs",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column(
            "room_id",
            sa.String(32),
            sa.ForeignKey("rooms.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("model", sa.String(16), nullable=False),
        sa.Column("solver", sa.String(32), nullable=False),
        sa.Column("targets", sa.Integer, nullable=True),
        sa.Column("min_terminals", sa.Integer, nullable=False),
        sa.Column("max_terminals", sa.Integer, nullable=False),
        sa.Column("window_s", sa.Float, nullable=False),
        sa.Column("fingerprint_version", sa.Integer, nullable=False),
        sa.Column("leds", sa.Integer, nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("expires_at", UTCDateTime(), nullable=False),
        sa.Column("attempts", sa.Integer, nullable=False),
        sa.Column("claim_owner", sa.String(64), nullable=True),
        sa.Column("claim_expires_at", UTCDateTime(), nullable=True),
        sa.Column("finished_at", UTCDateTime(), nullable=True),
        sa.Column("localization", sa.JSON, nullable=True),
        sa.Column("error", sa.Text, nullable=True),
    )
    op.create_index("ix_epochs_status_expires_at", "epochs", ["status", "expires_at"])
    op.create_index("ix_epochs_room_id", "epochs", ["room_id"])
    op.create_table(
        "epoch_measurements",
        sa.Column(
            "epoch_id",
            sa.String(32),
            sa.ForeignKey("epochs.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("terminal_id", sa.String(64), primary_key=True),
        sa.Column("amplitudes", sa.JSON, nullable=False),
        sa.Column("posted_at", UTCDateTime(), nullable=False),
    )


def downgrade() -> None:
    """Drop both tables."""
    op.drop_table("epoch_measurements")
    op.drop_table("epochs")
