"""Matrix files in the database: hosts that share only the database serve the same rooms.

Revision ID: 0005
Revises: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from app.registry._schema import UTCDateTime

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Create ``matrix_blobs`` (one row per file) and ``matrix_blob_chunks`` (its bytes)."""
    op.create_table(
        "matrix_blobs",
        sa.Column("sha256", sa.String(64), primary_key=True),
        sa.Column("format", sa.String(8), primary_key=True),
        sa.Column("upload_id", sa.String(32), nullable=False, unique=True),
        sa.Column("size_bytes", sa.BigInteger, nullable=False),
        sa.Column("n_chunks", sa.Integer, nullable=False),
        sa.Column("created_at", UTCDateTime(), nullable=False),
    )
    op.create_table(
        "matrix_blob_chunks",
        sa.Column(
            "upload_id",
            sa.String(32),
            sa.ForeignKey("matrix_blobs.upload_id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("chunk_index", sa.Integer, primary_key=True),
        sa.Column("data", sa.LargeBinary, nullable=False),
    )


def downgrade() -> None:
    """Drop both tables (files stored only there are lost; rebuild their rooms)."""
    op.drop_table("matrix_blob_chunks")
    op.drop_table("matrix_blobs")
