"""Fault, concurrency and scale-out test fixtures: the shared database fixtures."""

from __future__ import annotations

from tests.db_fixtures import database_url, postgres_url, registry, sqlite_url

__all__ = ["database_url", "postgres_url", "registry", "sqlite_url"]
