"""A typed Python client of the VLP service (httpx, synchronous).

>>> from app.client import VLPClient, NotFound
>>> issubclass(NotFound, Exception)
True
"""

from ._client import DEFAULT_TIMEOUT_S, ProgressCallback, VLPClient
from ._errors import (
    APIError,
    AuthenticationError,
    ClientError,
    Conflict,
    FieldProblem,
    InvalidRequest,
    JobError,
    JobFailed,
    JobTimeout,
    NotFound,
    PermissionDenied,
    PreconditionError,
    ServerError,
    TransportError,
)
from ._models import Epoch, Job
from ._tracks import TrackEvent

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "APIError",
    "AuthenticationError",
    "ClientError",
    "Conflict",
    "Epoch",
    "FieldProblem",
    "InvalidRequest",
    "Job",
    "JobError",
    "JobFailed",
    "JobTimeout",
    "NotFound",
    "PermissionDenied",
    "PreconditionError",
    "ProgressCallback",
    "ServerError",
    "TrackEvent",
    "TransportError",
    "VLPClient",
]
