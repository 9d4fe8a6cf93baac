"""Persistence: rooms, API keys, fingerprint metadata (SQL) and the matrix store (files).

SQLite in ``VLP_DATA_DIR`` by default, PostgreSQL when ``VLP_DATABASE_URL`` says so; the
schema is managed by the Alembic migrations in ``migrations/``. See :class:`Registry`.
"""

from __future__ import annotations

from .records import CalibrationRecord, FingerprintRecord, JobRecord, MatrixInfo, RoomRecord
from .registry import Registry

__all__ = [
    "CalibrationRecord",
    "FingerprintRecord",
    "JobRecord",
    "MatrixInfo",
    "Registry",
    "RoomRecord",
]
