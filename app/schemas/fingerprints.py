"""Fingerprint metadata and build jobs."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Literal

from pydantic import Field

from .common import ResponseModel
from .statuses import JobStatus

__all__ = ["Fingerprint", "FingerprintsList", "Job", "JobResult", "MatrixMeta", "MatrixName"]


class MatrixName(StrEnum):
    """The downloadable matrices of a fingerprint."""

    H = "H"
    J = "J"
    psi = "psi"


class MatrixMeta(ResponseModel):
    """One stored matrix: its shape, content hash and file format."""

    shape: list[int] = Field(examples=[[16, 400]])
    sha256: str = Field(description="hex sha256 of the downloadable file")
    format: Literal["npy", "npz"] = Field(description="`npz`: sparse H (download `H.npz`)")


class Fingerprint(ResponseModel):
    """An immutable fingerprint version: H (M x N) and the dictionaries J, psi built from it."""

    version: int
    room_id: str
    layout_version: int = Field(description="the room layout it was built from")
    leds: int = Field(description="M")
    grid_points: int = Field(description="N")
    built_at: datetime
    build_seconds: float
    matrices: dict[str, MatrixMeta] = Field(description="keys among `H`, `J`, `psi`")
    job_id: str | None
    calibration_id: str | None = Field(
        default=None, description="the survey calibration whose model it was built from"
    )
    masked_leds: list[int] = Field(
        default_factory=list,
        description="room LED indices left out (H has M minus these rows, in room order)",
    )


class FingerprintsList(ResponseModel):
    """A room's fingerprint versions, newest first."""

    items: list[Fingerprint]


class JobResult(ResponseModel):
    """What a succeeded job produced."""

    fingerprint_version: int
    calibration_id: str | None = Field(
        default=None, description="for a `calibration` job: the calibration (its report)"
    )


class Job(ResponseModel):
    """A background job: a fingerprint build or a survey calibration (`kind`)."""

    id: str
    kind: str = Field(examples=["build_fingerprint", "calibration"])
    room_id: str | None = Field(description="null once the room was deleted")
    status: JobStatus
    progress: float = Field(ge=0, le=1)
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    result: JobResult | None
    attempts: int = Field(ge=0, description="runs started so far (failed runs are retried)")
    layout_version: int = Field(description="the room layout this build is for")
