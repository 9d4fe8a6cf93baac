"""Epoch posts may leave LEDs undetected: each post keeps its terminal's detection floor.

Null amplitudes need no change (``amplitudes`` is a JSON array, which holds nulls); the
floor a terminal sent with them gets its own column, null when it sent none.

Revision ID: 0007
Revises: 0006
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add ``epoch_measurements.detection_floor`` (nullable: posts before it sent none)."""
    with op.batch_alter_table("epoch_measurements") as batch:
        batch.add_column(sa.Column("detection_floor", sa.Float, nullable=True))


def downgrade() -> None:
    """Drop ``epoch_measurements.detection_floor``."""
    with op.batch_alter_table("epoch_measurements") as batch:
        batch.drop_column("detection_floor")
