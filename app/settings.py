"""Service settings: one pydantic-settings class, read from ``VLP_*`` environment variables.

Tests override :func:`get_settings` (or pass a ``Settings`` to ``create_app``).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["MIN_KEY_LENGTH", "Settings", "get_settings"]

# Keys from the environment must be at least this long (generated ones have 47 characters).
MIN_KEY_LENGTH = 24


class Settings(BaseSettings):
    """Everything the service can be configured with (env prefix ``VLP_``)."""

    model_config = SettingsConfigDict(env_prefix="VLP_", extra="ignore")

    data_dir: Path = Field(default=Path("./var"), description="SQLite file and matrix store")
    database_url: str | None = Field(
        default=None, description="SQLAlchemy URL; postgresql+psycopg://... for scale-out"
    )
    matrix_store: Literal["auto", "files", "database"] = Field(
        default="auto",
        description="where fingerprint matrices are kept: `files` (under data_dir only), "
        "`database` (in the registry, data_dir as a verified cache: hosts sharing only the "
        "database serve the same rooms); `auto` is `database` on PostgreSQL, else `files`",
    )
    admin_keys: str = Field(
        default="", description=f"comma-separated admin API keys (>= {MIN_KEY_LENGTH} characters)"
    )
    terminal_keys: str = Field(
        default="",
        description=f"comma-separated terminal API keys (>= {MIN_KEY_LENGTH} characters)",
    )
    public_url: str = Field(
        default="http://127.0.0.1:8000",
        description="where clients reach the service (written to the credentials file; "
        "`vlp serve` sets it from --host/--port unless VLP_PUBLIC_URL is set)",
    )
    cors_origins: str = Field(
        default="",
        description="comma-separated origins a browser may call the API from (none: no CORS)",
    )
    embedded_workers: int = Field(default=1, ge=0, le=16)
    workers: int = Field(
        default=1,
        ge=1,
        le=64,
        description="API processes of `vlp serve` on its one port (`--workers`); the embedded "
        "build workers and the epoch sweeper run in the first one only",
    )
    demo: bool = Field(default=True, description="seed the paper's room into an empty registry")

    # Limits (security by default; the defaults admit a 10^6-point, 4096-LED hall).
    # See docs/explanation/reliability.md#hostile-input-and-security.
    max_body_bytes: int = Field(
        default=16 * 1024 * 1024, ge=1024, description="larger request bodies answer 413"
    )
    max_leds: int = Field(default=4096, ge=1, description="LEDs per room layout (else 422)")
    max_grid_points: int = Field(
        default=1_000_000, ge=1, description="grid points per room layout (else 422)"
    )
    max_localize_work: int = Field(
        default=100_000_000_000,
        ge=1,
        description="grid points x observations x targets one localize request may ask for "
        "(observations: M for power and terminals, M(M+1)/2 for correlation; K unknown counts "
        "as 64); larger requests answer 422. The default admits 64 targets in a "
        "10^6-point, 1024-LED hall as power or terminals, not its correlation matrix",
    )
    max_concurrent_builds_per_room: int = Field(
        default=1,
        ge=1,
        description="fingerprint builds of one room that workers run at once; rebuild "
        "requests beyond them coalesce into the room's one queued job",
    )

    # Jobs.
    job_lease_seconds: float = Field(default=30.0, gt=0)
    job_heartbeat_seconds: float = Field(default=5.0, gt=0)
    job_poll_seconds: float = Field(default=0.5, gt=0)
    max_build_attempts: int = Field(default=3, ge=1)

    # Cooperation epochs: the sweeper closes windows that passed (0 s: only lazily, on reads
    # and solve requests); a solve claim is a lease, taken over when its process is gone.
    epoch_sweep_seconds: float = Field(default=0.5, ge=0)
    epoch_solve_lease_seconds: float = Field(default=30.0, gt=0)
    epoch_max_solve_attempts: int = Field(default=3, ge=1)
    # At most the solvers' MAX_TARGETS (64): each terminal of an epoch is one target.
    epoch_max_terminals: int = Field(default=64, ge=1, le=64)
    epoch_retention_seconds: float = Field(default=86_400.0, gt=0)

    # Track streams: a reader with no news reads the registry again after this long (news
    # comes at once from this process, and on PostgreSQL from every process).
    track_stream_poll_seconds: float = Field(default=1.0, gt=0, le=60)

    # Localization cache: how often an API process re-reads a room's current version.
    version_check_seconds: float = Field(default=1.0, ge=0)
    fingerprint_cache_size: int = Field(default=16, ge=1)
    fingerprint_cache_mib: int = Field(
        default=1024,
        ge=1,
        description="arrays an API process keeps of loaded rooms and their prepared solvers "
        "(MiB); beyond it the least recently used rooms are dropped (the room in use is "
        "always kept)",
    )
    # The solver kernels: loaded by the first solve of a process (default), or at start.
    warm_kernels_at_start: bool = Field(
        default=False,
        description="load the solvers' compiled kernels (numba) before serving: the first "
        "localize of a process no longer waits for them, and every process holds them "
        "(about 150 MiB) whether it solves or not",
    )

    @field_validator("admin_keys", "terminal_keys")
    @classmethod
    def _keys_long_enough(cls, value: str) -> str:
        short = [key.strip() for key in value.split(",") if 0 < len(key.strip()) < MIN_KEY_LENGTH]
        if short:
            lengths = ", ".join(str(len(key)) for key in short)
            raise ValueError(
                f"API keys must have at least {MIN_KEY_LENGTH} characters; got {len(short)} "
                f"shorter (length {lengths}). Make one with: python -c "
                "'import secrets; print(secrets.token_urlsafe(32))'"
            )
        return value

    def resolved_database_url(self) -> str:
        """The registry URL: ``database_url`` or a SQLite file in ``data_dir``."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'registry.sqlite3').resolve()}"

    def resolved_matrix_store(self) -> Literal["files", "database"]:
        """The matrix store in force: ``matrix_store``, with ``auto`` resolved by backend."""
        if self.matrix_store != "auto":
            return self.matrix_store
        return "files" if self.resolved_database_url().startswith("sqlite") else "database"

    def admin_key_list(self) -> list[str]:
        """Configured admin keys (empty strings dropped)."""
        return [key.strip() for key in self.admin_keys.split(",") if key.strip()]

    def terminal_key_list(self) -> list[str]:
        """Configured terminal keys (empty strings dropped)."""
        return [key.strip() for key in self.terminal_keys.split(",") if key.strip()]

    def cors_origin_list(self) -> list[str]:
        """Origins allowed to call the API from a browser (empty: CORS off)."""
        return [origin.strip() for origin in self.cors_origins.split(",") if origin.strip()]


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
