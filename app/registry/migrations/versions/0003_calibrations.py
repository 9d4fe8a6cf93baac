"""Survey calibrations: their table, and which calibration a fingerprint version was built from.

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from app.registry._schema import UTCDateTime

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Create ``calibrations``; add ``calibration_id`` and ``masked_leds`` to ``fingerprints``."""
    op.create_table(
        "calibrations",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column(
            "room_id", sa.String(32), sa.ForeignKey("rooms.id", ondelete="CASCADE"), nullable=False
        ),
        sa.Column("layout_version", sa.Integer, nullable=False),
        sa.Column("job_id", sa.String(32), nullable=False),
        sa.Column("request", sa.JSON, nullable=False),
        sa.Column("based_on", sa.String(32), nullable=True),
        sa.Column("report", sa.JSON, nullable=True),
        sa.Column("calibrated_layout", sa.JSON, nullable=True),
        sa.Column("layout", sa.JSON, nullable=True),
        sa.Column("masked_leds", sa.JSON, nullable=True),
        sa.Column("fingerprint_version", sa.Integer, nullable=True),
        sa.Column("created_at", UTCDateTime(), nullable=False),
        sa.Column("finished_at", UTCDateTime(), nullable=True),
    )
    op.create_index("ix_calibrations_room_id_created_at", "calibrations", ["room_id", "created_at"])
    op.create_index("ix_calibrations_job_id", "calibrations", ["job_id"])
    with op.batch_alter_table("fingerprints") as batch:
        batch.add_column(sa.Column("calibration_id", sa.String(32), nullable=True))
        batch.add_column(sa.Column("masked_leds", sa.JSON, nullable=True))


def downgrade() -> None:
    """Drop what :func:`upgrade` added."""
    with op.batch_alter_table("fingerprints") as batch:
        batch.drop_column("masked_leds")
        batch.drop_column("calibration_id")
    op.drop_table("calibrations")
