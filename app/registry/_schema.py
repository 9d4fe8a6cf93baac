"""The registry's tables (SQLAlchemy Core). Schema changes go only through Alembic."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    DateTime,
    Dialect,
    Float,
    ForeignKey,
    ForeignKeyConstraint,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Table,
    Text,
    UniqueConstraint,
    true,
)
from sqlalchemy.types import TypeDecorator

__all__ = [
    "UTCDateTime",
    "api_keys",
    "calibrations",
    "epoch_measurements",
    "epochs",
    "fingerprints",
    "jobs",
    "matrices",
    "matrix_blob_chunks",
    "matrix_blobs",
    "metadata",
    "room_tracking",
    "rooms",
    "track_events",
    "track_points",
    "tracks",
]

metadata = MetaData()


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC datetime on every backend (SQLite stores it naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetimes are not stored; use datetime.now(UTC)")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        del dialect
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


ID = String(32)

api_keys = Table(
    "api_keys",
    metadata,
    Column("key_hash", String(64), primary_key=True),
    Column("id", ID, nullable=False),
    Column("role", String(16), nullable=False),
    Column("label", Text, nullable=False),
    # "api" (POST /v1/keys), "environment" (VLP_*_KEYS) or "generated" (first start).
    Column("source", String(16), nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("last_used_at", UTCDateTime(), nullable=True),
    # A revoked key's row stays, so the same key set again in the environment stays refused.
    Column("revoked_at", UTCDateTime(), nullable=True),
    UniqueConstraint("id", name="uq_api_keys_id"),
)

rooms = Table(
    "rooms",
    metadata,
    Column("id", ID, primary_key=True),
    Column("name", Text, nullable=False),
    Column("layout", JSON, nullable=False),
    Column("layout_version", Integer, nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("updated_at", UTCDateTime(), nullable=False),
    Column("current_version", Integer, nullable=True),
    Column("latest_job_id", ID, nullable=True),
    Index("ix_rooms_created_at_id", "created_at", "id"),
)

jobs = Table(
    "jobs",
    metadata,
    Column("id", ID, primary_key=True),
    Column("kind", String(32), nullable=False),
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), nullable=True),
    Column("status", String(16), nullable=False),
    Column("progress", Float, nullable=False),
    Column("error", Text, nullable=True),
    Column("attempts", Integer, nullable=False),
    Column("layout_version", Integer, nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("started_at", UTCDateTime(), nullable=True),
    Column("finished_at", UTCDateTime(), nullable=True),
    Column("fingerprint_version", Integer, nullable=True),
    Column("lease_owner", String(64), nullable=True),
    Column("lease_expires_at", UTCDateTime(), nullable=True),
    Column("heartbeat_at", UTCDateTime(), nullable=True),
    Index("ix_jobs_status_created_at", "status", "created_at"),
    Index("ix_jobs_room_id", "room_id"),
)

fingerprints = Table(
    "fingerprints",
    metadata,
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), primary_key=True),
    Column("version", Integer, primary_key=True),
    Column("layout_version", Integer, nullable=False),
    Column("layout", JSON, nullable=False),
    Column("leds", Integer, nullable=False),
    Column("grid_points", Integer, nullable=False),
    Column("built_at", UTCDateTime(), nullable=False),
    Column("build_seconds", Float, nullable=False),
    Column("job_id", ID, nullable=True),
    # Set when the version was built from a calibrated model (migration 0003).
    Column("calibration_id", ID, nullable=True),
    Column("masked_leds", JSON, nullable=True),
)

matrices = Table(
    "matrices",
    metadata,
    Column("room_id", ID, primary_key=True),
    Column("version", Integer, primary_key=True),
    Column("name", String(16), primary_key=True),
    Column("sha256", String(64), nullable=False),
    Column("format", String(8), nullable=False),
    Column("shape", JSON, nullable=False),
    Column("size_bytes", BigInteger, nullable=False),
    ForeignKeyConstraint(
        ["room_id", "version"],
        ["fingerprints.room_id", "fingerprints.version"],
        ondelete="CASCADE",
    ),
    Index("ix_matrices_sha256", "sha256"),
)

# Matrix files stored in the database (migration 0005), for hosts that share no filesystem:
# one row per content-addressed file, its bytes in ordered chunks. The head row and its
# chunks are written in one transaction, so a reader sees a whole file or none.
matrix_blobs = Table(
    "matrix_blobs",
    metadata,
    Column("sha256", String(64), primary_key=True),
    Column("format", String(8), primary_key=True),
    Column("upload_id", ID, nullable=False, unique=True),
    Column("size_bytes", BigInteger, nullable=False),
    Column("n_chunks", Integer, nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
)

matrix_blob_chunks = Table(
    "matrix_blob_chunks",
    metadata,
    Column(
        "upload_id",
        ID,
        ForeignKey("matrix_blobs.upload_id", ondelete="CASCADE"),
        primary_key=True,
    ),
    Column("chunk_index", Integer, primary_key=True),
    Column("data", LargeBinary, nullable=False),
)

# Cooperation epochs (migration 0002): one row per window; ``status`` is open -> solving ->
# solved | expired | failed, and the open -> solving step is a conditional update (the claim).
epochs = Table(
    "epochs",
    metadata,
    Column("id", ID, primary_key=True),
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), nullable=False),
    Column("status", String(16), nullable=False),
    Column("model", String(16), nullable=False),
    Column("solver", String(32), nullable=False),
    Column("targets", Integer, nullable=True),
    Column("min_terminals", Integer, nullable=False),
    Column("max_terminals", Integer, nullable=False),
    Column("window_s", Float, nullable=False),
    Column("fingerprint_version", Integer, nullable=False),
    Column("leds", Integer, nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("expires_at", UTCDateTime(), nullable=False),
    Column("attempts", Integer, nullable=False),
    Column("claim_owner", String(64), nullable=True),
    Column("claim_expires_at", UTCDateTime(), nullable=True),
    Column("finished_at", UTCDateTime(), nullable=True),
    Column("localization", JSON, nullable=True),
    Column("error", Text, nullable=True),
    # Whether the solved epoch updates the room's tracks (migration 0006).
    Column("track", Boolean, nullable=False, server_default=true()),
    Index("ix_epochs_status_expires_at", "status", "expires_at"),
    Index("ix_epochs_room_id", "room_id"),
)

epoch_measurements = Table(
    "epoch_measurements",
    metadata,
    Column("epoch_id", ID, ForeignKey("epochs.id", ondelete="CASCADE"), primary_key=True),
    Column("terminal_id", String(64), primary_key=True),
    # A JSON array of numbers and nulls (LEDs not detected); the floor is the terminal's own
    # (migration 0007), null when it sent none.
    Column("amplitudes", JSON, nullable=False),
    Column("posted_at", UTCDateTime(), nullable=False),
    Column("detection_floor", Float, nullable=True),
)

# A survey calibration (migration 0003): the request, and once its job succeeded the fit
# report and the layouts it produced. Its status is that of its job.
calibrations = Table(
    "calibrations",
    metadata,
    Column("id", ID, primary_key=True),
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), nullable=False),
    Column("layout_version", Integer, nullable=False),
    Column("job_id", ID, nullable=False),
    Column("request", JSON, nullable=False),
    Column("based_on", ID, nullable=True),
    Column("report", JSON, nullable=True),
    Column("calibrated_layout", JSON, nullable=True),
    Column("layout", JSON, nullable=True),
    Column("masked_leds", JSON, nullable=True),
    Column("fingerprint_version", Integer, nullable=True),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("finished_at", UTCDateTime(), nullable=True),
    Index("ix_calibrations_room_id_created_at", "room_id", "created_at"),
    Index("ix_calibrations_job_id", "job_id"),
)

# Tracking (migration 0006). One row per room that has ever tracked: its tracking settings
# (null: the defaults) and the sequence number of its newest stream event. Every update of a
# room's tracks locks this row first, so updates of one room are serialised on every backend.
room_tracking = Table(
    "room_tracking",
    metadata,
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), primary_key=True),
    Column("sequence", BigInteger, nullable=False),
    Column("settings", JSON, nullable=True),
)

# A track: the filter's state (``filter``: per-model means, covariances, probabilities), the
# public summary beside it, and the fix that last moved it. Ended tracks are deleted; ids are
# random and never reused.
tracks = Table(
    "tracks",
    metadata,
    Column("id", ID, primary_key=True),
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), nullable=False),
    Column("terminal_id", String(64), nullable=True),
    Column("status", String(16), nullable=False),
    Column("filter", JSON, nullable=False),
    Column("x", Float, nullable=False),
    Column("y", Float, nullable=False),
    Column("vx", Float, nullable=False),
    Column("vy", Float, nullable=False),
    Column("covariance", JSON, nullable=False),
    Column("accuracy_m", Float, nullable=False),
    Column("state_time", UTCDateTime(), nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
    Column("updated_at", UTCDateTime(), nullable=False),
    Column("updates", Integer, nullable=False),
    Column("misses", Integer, nullable=False),
    Column("last_raw", JSON, nullable=True),
    UniqueConstraint("room_id", "terminal_id", name="uq_tracks_room_terminal"),
    Index("ix_tracks_room_id_created_at", "room_id", "created_at"),
)

# A track's bounded history: the state after each fix, and the fix.
track_points = Table(
    "track_points",
    metadata,
    Column(
        "id", BigInteger().with_variant(Integer, "sqlite"), primary_key=True, autoincrement=True
    ),
    Column("track_id", ID, ForeignKey("tracks.id", ondelete="CASCADE"), nullable=False),
    Column("room_id", ID, nullable=False),
    Column("time", UTCDateTime(), nullable=False),
    Column("x", Float, nullable=False),
    Column("y", Float, nullable=False),
    Column("accuracy_m", Float, nullable=False),
    Column("raw_x", Float, nullable=True),
    Column("raw_y", Float, nullable=True),
    Column("raw_accuracy_m", Float, nullable=True),
    Index("ix_track_points_track_id_id", "track_id", "id"),
    Index("ix_track_points_room_id_time", "room_id", "time"),
)

# The room's stream: one row per event, numbered per room; kept for the history window so a
# client that reconnects with Last-Event-ID gets what it missed.
track_events = Table(
    "track_events",
    metadata,
    Column("room_id", ID, ForeignKey("rooms.id", ondelete="CASCADE"), primary_key=True),
    Column("sequence", BigInteger, primary_key=True),
    Column("kind", String(16), nullable=False),
    Column("track_id", ID, nullable=False),
    Column("data", JSON, nullable=False),
    Column("created_at", UTCDateTime(), nullable=False),
)
