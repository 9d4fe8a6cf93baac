"""Every error family of the service, in one place.

The tree::

    VLPError (ValueError)            the science core refuses an input (app.vlp.errors)
    ├── GeometryError                an invalid room layout
    ├── MeasurementError             a measurement of the wrong shape, sign or value
    ├── ProblemSizeError             a problem above a configured limit
    └── SolverError
        ├── UnknownSolverError
        └── SolverFailed             a valid problem the solver found no answer to (503)
    RegistryError                    the registry refuses or cannot do (app.registry.errors)
    ├── RecordNotFound
    │   ├── RoomNotFound, JobNotFound, FingerprintNotFound, MatrixNotFound, EpochNotFound,
    │   └── TrackNotFound
    ├── StateConflict
    │   ├── EpochClosed, EpochFull
    ├── PreconditionFailed, FingerprintNotReady, CorruptMatrix, InvalidCursor
    └── RegistryUnavailable
    InvalidFields (ValueError)       the service layer refuses a request, naming each field

``app.api.errors`` maps each family to an HTTP problem answer.
"""

from __future__ import annotations

from collections.abc import Sequence

from app.registry.errors import (
    CorruptMatrix,
    EpochClosed,
    EpochFull,
    EpochNotFound,
    FingerprintNotFound,
    FingerprintNotReady,
    InvalidCursor,
    JobNotFound,
    MatrixNotFound,
    PreconditionFailed,
    RecordNotFound,
    RegistryError,
    RegistryUnavailable,
    RoomNotFound,
    StateConflict,
    TrackNotFound,
)
from app.vlp.errors import (
    GeometryError,
    MeasurementError,
    ProblemSizeError,
    SolverError,
    SolverFailed,
    UnknownSolverError,
    VLPError,
)

__all__ = [
    "CorruptMatrix",
    "EpochClosed",
    "EpochFull",
    "EpochNotFound",
    "FingerprintNotFound",
    "FingerprintNotReady",
    "GeometryError",
    "InvalidCursor",
    "InvalidFields",
    "JobNotFound",
    "MatrixNotFound",
    "MeasurementError",
    "PreconditionFailed",
    "ProblemSizeError",
    "RecordNotFound",
    "RegistryError",
    "RegistryUnavailable",
    "RoomNotFound",
    "SolverError",
    "SolverFailed",
    "StateConflict",
    "TrackNotFound",
    "UnknownSolverError",
    "VLPError",
]


class InvalidFields(ValueError):
    """A request the service layer refuses for more than one field at once (the science core
    names one field per error).

    ``errors`` holds ``(field, message)`` pairs; fields are paths in the request body as the
    science core writes them (``"power"``, ``"terminals[1].id"``).
    """

    def __init__(self, errors: Sequence[tuple[str, str]]) -> None:
        self.errors = list(errors)
        super().__init__("; ".join(f"{field}: {message}" for field, message in self.errors))
