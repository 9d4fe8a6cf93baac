"""Answer types the client needs beyond :mod:`app.schemas`.

Rooms, fingerprints, simulations and localizations come back as the service's own pydantic
models. Jobs and epochs get the lenient models below: jobs of other kinds (calibration)
carry a different ``result``, and the epoch answer is not among the server's schemas on
every version the client may talk to.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from app.schemas import Localization
from app.schemas.statuses import EpochStatus, JobStatus

__all__ = ["Epoch", "Job"]


class Job(BaseModel):
    """A background job (fingerprint build or calibration), as the client sees it."""

    model_config = ConfigDict(extra="allow")

    id: str
    kind: str
    room_id: str | None = None
    status: JobStatus
    progress: float = Field(default=0.0, ge=0, le=1)
    error: str | None = None
    created_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None
    result: dict[str, Any] | None = Field(
        default=None, description="builds: `fingerprint_version`; calibrations: their id"
    )

    @property
    def finished(self) -> bool:
        """Whether the job has ended (succeeded or failed)."""
        return self.status in ("succeeded", "failed")


class Epoch(BaseModel):
    """A cooperation window that terminals join one by one (docs/how-to/use-epochs.md)."""

    model_config = ConfigDict(extra="allow")

    id: str
    room_id: str
    status: EpochStatus
    terminals: int = Field(ge=0, description="terminals that posted so far")
    expires_at: datetime | None = None
    localization: Localization | None = None
