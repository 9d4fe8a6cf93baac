"""Errors raised by :class:`app.client.VLPClient`.

The tree::

    ClientError                  anything the client raises on purpose
    ├── TransportError           no answer: connection refused, timeout, protocol error
    ├── APIError                 the service answered with a problem (4xx/5xx)
    │   ├── AuthenticationError  401: missing or unknown key
    │   ├── PermissionDenied     403: known key, wrong role
    │   ├── NotFound             404
    │   ├── Conflict             409: e.g. no fingerprint ready yet, epoch closed
    │   ├── PreconditionError    412 / 428: stale or missing If-Match
    │   ├── InvalidRequest       400 / 413 / 415 / 422: `errors` names each bad field
    │   └── ServerError          5xx
    └── JobError                 a background job did not succeed
        ├── JobFailed            it ended `failed`
        └── JobTimeout           it did not finish in time

httpx errors are translated once, in ``_client.py``, and re-raised ``from`` the original.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "APIError",
    "AuthenticationError",
    "ClientError",
    "Conflict",
    "FieldProblem",
    "InvalidRequest",
    "JobError",
    "JobFailed",
    "JobTimeout",
    "NotFound",
    "PermissionDenied",
    "PreconditionError",
    "ServerError",
    "TransportError",
    "api_error_from_answer",
]


class ClientError(Exception):
    """Base of every error the VLP client raises."""


class TransportError(ClientError):
    """The request got no answer (connection refused, timeout, broken connection)."""


@dataclass(frozen=True)
class FieldProblem:
    """One invalid input named by a validation problem (`errors[]` of the answer)."""

    field: str
    message: str


class APIError(ClientError):
    """The service answered with an RFC 9457 problem.

    Parameters
    ----------
    status : int
        HTTP status code.
    title : str
        Short summary of the kind of problem.
    detail : str
        What happened in this case.
    problem : Mapping
        The whole problem body as received (empty when the answer was not a problem).
    """

    def __init__(self, status: int, title: str, detail: str, problem: Mapping[str, Any]) -> None:
        super().__init__(f"{status} {title}: {detail}")
        self.status = status
        self.title = title
        self.detail = detail
        self.problem: dict[str, Any] = dict(problem)
        self.type: str = str(problem.get("type", "about:blank"))
        self.instance: str | None = problem.get("instance")
        self.request_id: str | None = problem.get("request_id")
        self.errors: list[FieldProblem] = [
            FieldProblem(field=str(item.get("field", "")), message=str(item.get("message", "")))
            for item in problem.get("errors") or []
            if isinstance(item, Mapping)
        ]


class AuthenticationError(APIError):
    """401: the key is missing or unknown."""


class PermissionDenied(APIError):
    """403: the key is known but its role may not do this."""


class NotFound(APIError):
    """404: no such room, job, fingerprint version, epoch or calibration."""


class Conflict(APIError):
    """409: the resource is not in a state that allows this (e.g. no fingerprint yet)."""


class PreconditionError(APIError):
    """412 or 428: the `If-Match` ETag is stale or missing."""


class InvalidRequest(APIError):
    """400, 413, 415 or 422: the request itself is wrong; `errors` names the fields."""


class ServerError(APIError):
    """5xx: the service failed or is unavailable; retrying later may help."""


class JobError(ClientError):
    """A background job did not succeed; ``job`` is its last state."""

    def __init__(self, message: str, job: Any) -> None:
        super().__init__(message)
        self.job = job


class JobFailed(JobError):
    """The job ended with status `failed`."""


class JobTimeout(JobError):
    """The job had not finished when the wait ran out."""


_BY_STATUS: dict[int, type[APIError]] = {
    400: InvalidRequest,
    401: AuthenticationError,
    403: PermissionDenied,
    404: NotFound,
    409: Conflict,
    412: PreconditionError,
    413: InvalidRequest,
    415: InvalidRequest,
    422: InvalidRequest,
    428: PreconditionError,
}


def api_error_from_answer(status: int, body: Any, reason: str) -> APIError:
    """The :class:`APIError` subclass for an error answer.

    Parameters
    ----------
    status : int
        HTTP status code (>= 400).
    body : Any
        The decoded JSON body, or None when the answer was not JSON.
    reason : str
        The HTTP reason phrase, used as title when the body is not a problem.

    Returns
    -------
    APIError
        An instance of the subclass for ``status`` (``ServerError`` for 5xx, ``APIError``
        for other unmapped codes).
    """
    problem: Mapping[str, Any] = body if isinstance(body, Mapping) else {}
    title = str(problem.get("title") or reason or "HTTP error")
    detail = str(problem.get("detail") or title)
    kind = _BY_STATUS.get(status, ServerError if status >= 500 else APIError)
    return kind(status, title, detail, problem)
