"""Tracks of moving terminals: per-room tracking state, tracks, their points, the stream.

Revision ID: 0006
Revises: 0005
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from app.registry._schema import UTCDateTime

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

_ID = sa.String(32)


def _room_fk() -> sa.ForeignKey:
    return sa.ForeignKey("rooms.id", ondelete="CASCADE")


def upgrade() -> None:
    """Create ``room_tracking``, ``tracks``, ``track_points`` and ``track_events``; epochs get
    ``track`` (true: a solved epoch updates the tracks)."""
    op.create_table(
        "room_tracking",
        sa.Column("room_id", _ID, _room_fk(), primary_key=True),
        sa.Column("sequence", sa.BigInteger, nullable=False),
        sa.Column("settings", sa.JSON, nullable=True),
    )
    op.create_table(
        "tracks",
        sa.Column("id", _ID, primary_key=True),
        sa.Column("room_id", _ID, _room_fk(), nullable=False),
        sa.Column("terminal_id", sa.String(64), nullable=True),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("filter", sa.JSON, nullable=False),
        sa.Column("x", sa.Float, nullable=False),
        sa.Column("y", sa.Float, nullable=False),
        sa.Column("vx", sa.Float, nullable=False),
        sa.Column("vy", sa.Float, nullable=False),
        sa.Column("covariance", sa.JSON, nullable=False),
        sa.Column("accuracy_m", sa.Float, nullable=False),
        sa.Column("state_time", UTCDateTime(), nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("updated_at", UTCDateTime(), nullable=False),
        sa.Column("updates", sa.Integer, nullable=False),
        sa.Column("misses", sa.Integer, nullable=False),
        sa.Column("last_raw", sa.JSON, nullable=True),
        sa.UniqueConstraint("room_id", "terminal_id", name="uq_tracks_room_terminal"),
    )
    op.create_index("ix_tracks_room_id_created_at", "tracks", ["room_id", "created_at"])
    op.create_table(
        "track_points",
        sa.Column(
            "id",
            sa.BigInteger().with_variant(sa.Integer, "sqlite"),
            primary_key=True,
            autoincrement=True,
        ),
        sa.Column("track_id", _ID, sa.ForeignKey("tracks.id", ondelete="CASCADE"), nullable=False),
        sa.Column("room_id", _ID, nullable=False),
        sa.Column("time", UTCDateTime(), nullable=False),
        sa.Column("x", sa.Float, nullable=False),
        sa.Column("y", sa.Float, nullable=False),
        sa.Column("accuracy_m", sa.Float, nullable=False),
        sa.Column("raw_x", sa.Float, nullable=True),
        sa.Column("raw_y", sa.Float, nullable=True),
        sa.Column("raw_accuracy_m", sa.Float, nullable=True),
    )
    op.create_index("ix_track_points_track_id_id", "track_points", ["track_id", "id"])
    op.create_index("ix_track_points_room_id_time", "track_points", ["room_id", "time"])
    op.create_table(
        "track_events",
        sa.Column("room_id", _ID, _room_fk(), primary_key=True),
        sa.Column("sequence", sa.BigInteger, primary_key=True),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("track_id", _ID, nullable=False),
        sa.Column("data", sa.JSON, nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
    )
    with op.batch_alter_table("epochs") as batch:
        batch.add_column(sa.Column("track", sa.Boolean, nullable=False, server_default=sa.true()))


def downgrade() -> None:
    """Drop the tracking tables and the epochs' ``track`` column."""
    with op.batch_alter_table("epochs") as batch:
        batch.drop_column("track")
    op.drop_table("track_events")
    op.drop_table("track_points")
    op.drop_table("tracks")
    op.drop_table("room_tracking")
