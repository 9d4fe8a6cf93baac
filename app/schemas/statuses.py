"""Every status vocabulary of the service, defined once.

The schemas type their ``status`` fields with these, the registry's records and rows use
them, and the client's lenient models reuse them, so a status is spelled in one place.
"""

from __future__ import annotations

from typing import Literal, get_args

__all__ = [
    "EPOCH_FINAL_STATUSES",
    "JOB_ACTIVE_STATUSES",
    "JOB_FINAL_STATUSES",
    "JOB_STATUSES",
    "EpochState",
    "EpochStatus",
    "FingerprintStatus",
    "JobStatus",
]

JobStatus = Literal["queued", "running", "succeeded", "failed"]
"""A job (build or calibration): queued -> running -> succeeded | failed."""
JOB_STATUSES: tuple[JobStatus, ...] = get_args(JobStatus)
JOB_ACTIVE_STATUSES: tuple[JobStatus, ...] = ("queued", "running")
JOB_FINAL_STATUSES: tuple[JobStatus, ...] = ("succeeded", "failed")

FingerprintStatus = Literal["pending", "building", "ready", "failed"]
"""A room's fingerprint, from its latest build job (queued -> pending, running -> building,
succeeded -> ready, failed -> failed)."""

EpochStatus = Literal["open", "solved", "expired", "failed"]
"""An epoch as answered (one being solved is still ``open`` to its terminals)."""
EpochState = Literal[EpochStatus, "solving"]
"""An epoch as stored: ``solving`` while a process holds its claim."""
EPOCH_FINAL_STATUSES: tuple[EpochStatus, ...] = ("solved", "expired", "failed")
