"""Every error family of the service, in one place.

The tree::

    VLPError (ValueError)            the science core refuses an input (app.vlp.errors)
    ├── GeometryError                an invalid room layout
    ├── MeasurementError             a measurement of the wrong shape, sign or value
    ├── ProblemSizeError             a problem above a configured limit
    └── SolverError
        └── UnknownSolverError
    RegistryError                    the registry refuses or cannot do (app.registry.errors)
    ├── NotFound
    │   ├── RoomNotFound, JobNotFound, FingerprintNotFound, MatrixNotFound, EpochNotFound
    ├── Conflict
    │   ├── EpochClosed, EpochFull
    ├── PreconditionFailed, FingerprintNotReady, CorruptMatrix, InvalidCursor
    └── RegistryUnavailable

``app.api.errors`` maps each family to an HTTP problem answer.
"""

from __future__ import annotations

from app.registry.errors import (
    Conflict,
    CorruptMatrix,
    EpochClosed,
    EpochFull,
    EpochNotFound,
    FingerprintNotFound,
    FingerprintNotReady,
    InvalidCursor,
    JobNotFound,
    MatrixNotFound,
    NotFound,
    PreconditionFailed,
    RegistryError,
    RegistryUnavailable,
    RoomNotFound,
)
from app.vlp.errors import (
    GeometryError,
    MeasurementError,
    ProblemSizeError,
    SolverError,
    UnknownSolverError,
    VLPError,
)

__all__ = [
    "Conflict",
    "CorruptMatrix",
    "EpochClosed",
    "EpochFull",
    "EpochNotFound",
    "FingerprintNotFound",
    "FingerprintNotReady",
    "GeometryError",
    "InvalidCursor",
    "JobNotFound",
    "MatrixNotFound",
    "MeasurementError",
    "NotFound",
    "PreconditionFailed",
    "ProblemSizeError",
    "RegistryError",
    "RegistryUnavailable",
    "RoomNotFound",
    "SolverError",
    "UnknownSolverError",
    "VLPError",
]
