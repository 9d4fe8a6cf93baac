"""Every error becomes an RFC 9457 problem (``application/problem+json``).

One place maps the error families (``app.errors``) and the framework's own errors (404, 405,
request validation) to problem answers; handlers raise, they never build error bodies.
:class:`ProblemKind` is the one table of problem kinds (``type`` is
``urn:vlp:problem:<kind>``); ``_REGISTRY_PROBLEMS`` and ``_SCIENCE_PROBLEMS`` give each error
class its status and kind.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from enum import StrEnum
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.errors import (
    CorruptMatrix,
    FingerprintNotReady,
    InvalidCursor,
    InvalidFields,
    MatrixNotFound,
    PreconditionFailed,
    RecordNotFound,
    RegistryError,
    RegistryUnavailable,
    SolverFailed,
    StateConflict,
    VLPError,
)
from app.schemas import Problem

__all__ = [
    "PROBLEM_MEDIA_TYPE",
    "ApiProblem",
    "InvalidInput",
    "ProblemKind",
    "as_problem",
    "field_location",
    "install_error_handlers",
    "problem_body",
    "problem_example",
    "problem_response",
    "problem_responses",
]

PROBLEM_MEDIA_TYPE = "application/problem+json"
_TYPE_PREFIX = "urn:vlp:problem:"


class ProblemKind(StrEnum):
    """Every kind of problem the service answers (the ``type`` is ``urn:vlp:problem:<kind>``)."""

    VALIDATION = "validation"
    BAD_REQUEST = "bad-request"
    UNSUPPORTED_MEDIA_TYPE = "unsupported-media-type"
    PAYLOAD_TOO_LARGE = "payload-too-large"
    UNAUTHORIZED = "unauthorized"
    FORBIDDEN = "forbidden"
    NOT_FOUND = "not-found"
    CONFLICT = "conflict"
    FINGERPRINT_NOT_READY = "fingerprint-not-ready"
    MATRIX_NOT_MATERIALISED = "matrix-not-materialised"
    MATRIX_FORMAT = "matrix-format"
    PRECONDITION_FAILED = "precondition-failed"
    PRECONDITION_REQUIRED = "precondition-required"
    NOT_READY = "not-ready"
    CORRUPT_MATRIX = "corrupt-matrix"
    REGISTRY_UNAVAILABLE = "registry-unavailable"
    REGISTRY_ERROR = "registry-error"
    SOLVER_FAILED = "solver-failed"
    INTERNAL = "internal"

    @property
    def type_uri(self) -> str:
        """The problem's ``type`` member."""
        return f"{_TYPE_PREFIX}{self.value}"


# Each registry error class's status and kind; the first matching row wins (subclasses first).
_REGISTRY_PROBLEMS: tuple[tuple[type[RegistryError], int, ProblemKind], ...] = (
    (MatrixNotFound, 409, ProblemKind.MATRIX_NOT_MATERIALISED),
    (RecordNotFound, 404, ProblemKind.NOT_FOUND),
    (PreconditionFailed, 412, ProblemKind.PRECONDITION_FAILED),
    (FingerprintNotReady, 409, ProblemKind.FINGERPRINT_NOT_READY),
    (StateConflict, 409, ProblemKind.CONFLICT),
    (InvalidCursor, 422, ProblemKind.VALIDATION),
    (CorruptMatrix, 503, ProblemKind.CORRUPT_MATRIX),
    (RegistryUnavailable, 503, ProblemKind.REGISTRY_UNAVAILABLE),
)
# The science core's: a solver that found no answer is the server's failure, not the input's
# (503: another solver, or the same one later under less load, may answer); the rest is
# invalid input.
_SCIENCE_PROBLEMS: tuple[tuple[type[VLPError], int, ProblemKind], ...] = (
    (SolverFailed, 503, ProblemKind.SOLVER_FAILED),
    (VLPError, 422, ProblemKind.VALIDATION),
)
_INDEX = re.compile(r"\[(\d+)\]")


class ApiProblem(Exception):
    """An HTTP problem raised by a handler or dependency."""

    def __init__(
        self,
        status: int,
        detail: str,
        *,
        kind: ProblemKind | None = None,
        title: str | None = None,
        errors: Sequence[tuple[str, str]] = (),
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = kind
        self.title = title
        self.errors = list(errors)
        self.headers = dict(headers or {})


class InvalidInput(ApiProblem):
    """A 422 naming the invalid fields: ``errors`` holds ``(field, message)`` pairs."""

    def __init__(self, errors: Sequence[tuple[str, str]]) -> None:
        detail = "; ".join(f"{field}: {message}" for field, message in errors)
        super().__init__(
            422, detail, kind=ProblemKind.VALIDATION, title="Validation failed", errors=errors
        )


def field_location(field: str | None, prefix: str = "body") -> str:
    """A science-core field (``"leds[3].z"``) as a request location (``"body.leds.3.z"``)."""
    if not field:
        return prefix
    dotted = _INDEX.sub(r".\1", field)
    return f"{prefix}.{dotted}"


def problem_body(
    status: int,
    detail: str,
    *,
    instance: str,
    kind: ProblemKind | None = None,
    title: str | None = None,
    errors: Iterable[tuple[str, str]] = (),
    request_id: str | None = None,
) -> dict[str, Any]:
    """The problem object for one error (the body of an answer, or an item of a batch's)."""
    phrase = HTTPStatus(status).phrase if status in HTTPStatus._value2member_map_ else "Error"
    body: dict[str, Any] = {
        "type": kind.type_uri if kind else "about:blank",
        "title": title or phrase,
        "status": status,
        "detail": detail,
        "instance": instance,
    }
    error_list = [{"field": field, "message": message} for field, message in errors]
    if error_list:
        body["errors"] = error_list
    if request_id:
        body["request_id"] = request_id
    return body


def problem_response(
    request: Request,
    status: int,
    detail: str,
    *,
    kind: ProblemKind | None = None,
    title: str | None = None,
    errors: Iterable[tuple[str, str]] = (),
    headers: Mapping[str, str] | None = None,
) -> JSONResponse:
    """The problem answer for one error."""
    body = problem_body(
        status,
        detail,
        instance=request.url.path,
        kind=kind,
        title=title,
        errors=errors,
        request_id=getattr(request.state, "request_id", None),
    )
    return JSONResponse(
        body, status_code=status, headers=dict(headers or {}), media_type=PROBLEM_MEDIA_TYPE
    )


def _validation_errors(exc: RequestValidationError) -> list[tuple[str, str]]:
    errors = []
    for error in exc.errors():
        loc = [str(part) for part in error.get("loc", ())]
        message = str(error.get("msg", "invalid"))
        if error.get("type") == "json_invalid":
            # FastAPI puts the parser's character offset where a field path goes
            # (`body.35`); it is no field, so name the body and say where it broke.
            where = f" at character {loc[1]}" if len(loc) > 1 else ""
            reason = error.get("ctx", {}).get("error", "")
            message = f"the body is not valid JSON{where} (counted from 0): {reason}"
            loc = loc[:1]
        errors.append((".".join(loc) or "body", message))
    return errors


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (
        media.startswith("application/") and media.endswith("+json")
    )


def _unsupported_media(request: Request, exc: RequestValidationError) -> str | None:
    """Why a body that is not declared JSON was refused (None when that is not the cause).

    FastAPI does not parse a body without a JSON ``Content-Type``, so the model sees bytes and
    answers a puzzling 422; a 415 says what to send instead.
    """
    content_type = request.headers.get("content-type", "")
    sent_body = request.headers.get("content-length", "0") != "0" or (
        "transfer-encoding" in request.headers
    )
    body_error = any(tuple(error.get("loc", ()))[:1] == ("body",) for error in exc.errors())
    if not body_error or not sent_body or _is_json(content_type):
        return None
    got = f"Content-Type {content_type}" if content_type else "no Content-Type"
    return f"send the body as JSON with Content-Type: application/json (got {got})"


def _registry_status(exc: RegistryError) -> tuple[int, ProblemKind]:
    for cls, status, kind in _REGISTRY_PROBLEMS:
        if isinstance(exc, cls):
            return status, kind
    return 500, ProblemKind.REGISTRY_ERROR


def _science_status(exc: VLPError) -> tuple[int, ProblemKind]:
    for cls, status, kind in _SCIENCE_PROBLEMS:
        if isinstance(exc, cls):
            return status, kind
    return 422, ProblemKind.VALIDATION


def as_problem(exc: Exception) -> ApiProblem:
    """The problem a service, science or registry error is answered with: the one mapping
    the handlers below and a batch's items (``app.api.localize_batch``) use.

    Raises
    ------
    TypeError
        For an exception that is none of those (a programming error: answered as a 500).
    """
    if isinstance(exc, ApiProblem):
        return exc
    if isinstance(exc, InvalidFields):
        return InvalidInput([(field_location(field), message) for field, message in exc.errors])
    if isinstance(exc, VLPError):
        status, kind = _science_status(exc)
        if status != 422:  # not the input's fault: no field to correct
            return ApiProblem(status, exc.message, kind=kind)
        errors = [(field_location(exc.field), exc.message)]
        return ApiProblem(422, exc.message, kind=kind, title="Validation failed", errors=errors)
    if isinstance(exc, RegistryError):
        status, kind = _registry_status(exc)
        errors = [(field_location(exc.field, "query"), exc.message)] if status == 422 else []
        headers = {"Retry-After": "5"} if status == 503 else None
        return ApiProblem(status, exc.message, kind=kind, errors=errors, headers=headers)
    raise TypeError(f"no problem mapping for {type(exc).__name__}")


def _unreadable_body(exc: StarletteHTTPException) -> str | None:
    """Why a JSON body could not be parsed, when FastAPI's bare 400 hides it (else None).

    Broken JSON is a 422 naming the body; so are JSON texts the parser gives up on.
    """
    cause = exc.__cause__
    if exc.status_code != 400 or cause is None:
        return None
    if isinstance(cause, UnicodeDecodeError):
        return f"the body is not valid JSON: not UTF-8 text ({cause.reason})"
    if isinstance(cause, RecursionError):
        return "the body is not valid JSON here: arrays or objects nested too deeply"
    if isinstance(cause, ValueError):  # e.g. an integer of more than 4300 digits
        return "the body is not valid JSON here: a number with too many digits"
    return None


def _path_pattern(template: str, operation: dict[str, Any]) -> str:
    """The regular expression of an OpenAPI path: each ``{parameter}`` as its declared
    ``pattern`` (``/tracks/stream`` is not ``/tracks/{track_id}``), else any segment."""
    declared = {
        parameter["name"]: parameter.get("schema", {}).get("pattern")
        for parameter in operation.get("parameters", [])
        if parameter.get("in") == "path"
    }
    parts = []
    for part in re.split(r"(\{[^/]+?\})", template):
        if part.startswith("{") and part.endswith("}"):
            pattern = declared.get(part[1:-1])
            parts.append(
                f"(?:{pattern.removeprefix('^').removesuffix('$')})" if pattern else "[^/]+"
            )
        else:
            parts.append(re.escape(part))
    return "".join(parts)


def _allowed_methods(app: FastAPI, path: str) -> str:
    methods: set[str] = set()
    for template, operations in app.openapi().get("paths", {}).items():
        for method, operation in operations.items():
            if re.fullmatch(_path_pattern(template, operation), path):
                methods.add(method.upper())
    return ", ".join(sorted(methods))


def install_error_handlers(app: FastAPI) -> None:
    """Register the problem handlers on ``app``."""

    async def on_api_problem(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ApiProblem)
        return problem_response(
            request,
            exc.status,
            exc.detail,
            kind=exc.kind,
            title=exc.title,
            errors=exc.errors,
            headers=exc.headers,
        )

    async def on_http(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        reason = _unreadable_body(exc)
        if reason is not None:
            return await on_api_problem(request, InvalidInput([("body", reason)]))
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            headers["Allow"] = _allowed_methods(app, request.url.path)
        return problem_response(request, exc.status_code, str(exc.detail), headers=headers)

    async def on_validation(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        unsupported = _unsupported_media(request, exc)
        if unsupported is not None:
            return problem_response(
                request,
                415,
                unsupported,
                kind=ProblemKind.UNSUPPORTED_MEDIA_TYPE,
                errors=[("header.content-type", unsupported)],
            )
        errors = _validation_errors(exc)
        return problem_response(
            request,
            422,
            f"{len(errors)} invalid input(s): " + "; ".join(f"{f}: {m}" for f, m in errors),
            kind=ProblemKind.VALIDATION,
            title="Validation failed",
            errors=errors,
        )

    async def on_domain_error(request: Request, exc: Exception) -> JSONResponse:
        return await on_api_problem(request, as_problem(exc))

    app.add_exception_handler(ApiProblem, on_api_problem)
    app.add_exception_handler(InvalidFields, on_domain_error)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(VLPError, on_domain_error)
    app.add_exception_handler(RegistryError, on_domain_error)


# (kind, detail, errors) of a typical answer of each status, as the handlers write them.
_ROOM_ID = "0f3c9a6e5b2d4c1a8e7f6a5b4c3d2e1f"
_EXAMPLES: dict[int, tuple[ProblemKind, str, list[dict[str, str]]]] = {
    401: (
        ProblemKind.UNAUTHORIZED,
        "this endpoint needs an API key in the X-API-Key header",
        [],
    ),
    403: (ProblemKind.FORBIDDEN, "the terminal role may not do this; it needs an admin key", []),
    404: (ProblemKind.NOT_FOUND, f"no room with id '{_ROOM_ID}'", []),
    409: (
        ProblemKind.FINGERPRINT_NOT_READY,
        f"room {_ROOM_ID} has no ready fingerprint yet",
        [],
    ),
    412: (
        ProblemKind.PRECONDITION_FAILED,
        'If-Match "1" is not the room\'s current ETag "2"; read the room again',
        [],
    ),
    413: (ProblemKind.PAYLOAD_TOO_LARGE, "request body larger than 16777216 bytes", []),
    422: (
        ProblemKind.VALIDATION,
        "body.grid.step: Input should be greater than 0",
        [{"field": "body.grid.step", "message": "Input should be greater than 0"}],
    ),
    428: (
        ProblemKind.PRECONDITION_REQUIRED,
        "send the room's current ETag in If-Match to replace it",
        [],
    ),
    503: (
        ProblemKind.REGISTRY_UNAVAILABLE,
        "the registry database is unavailable or busy; try again",
        [],
    ),
}


def problem_example(status: int) -> dict[str, Any]:
    """A problem body of ``status`` as the service answers it (the OpenAPI example).

    A status without an entry in ``_EXAMPLES`` gets a plain one from its description.
    """
    entry = _EXAMPLES.get(status)
    kind, detail, errors = entry or (None, _DESCRIPTIONS.get(status, ""), [])
    body: dict[str, Any] = {
        "type": kind.type_uri if kind else "about:blank",
        "title": "Validation failed" if status == 422 else HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
        "instance": f"/v1/rooms/{_ROOM_ID}",
    }
    if errors:
        body["errors"] = errors
    body["request_id"] = "9b2e4f6a8c0d4e1fa3b5c7d9e1f2a4b6"
    return body


def _problem_doc(status: int) -> dict[str, Any]:
    return {
        "description": _DESCRIPTIONS[status],
        "model": Problem,
        "content": {
            PROBLEM_MEDIA_TYPE: {
                "schema": {"$ref": "#/components/schemas/Problem"},
                "example": problem_example(status),
            }
        },
    }


_DESCRIPTIONS = {
    401: "no or unknown `X-API-Key`",
    403: "the key's role may not do this",
    404: "unknown room, job, epoch or fingerprint version",
    409: "conflict with the resource's state (e.g. no fingerprint ready yet)",
    412: "`If-Match` does not match the room's current `ETag`",
    413: "request body larger than the configured limit",
    415: "the body is not declared JSON (`Content-Type: application/json`)",
    422: "invalid input; `errors` names each field",
    428: "`If-Match` header missing",
    503: "the registry is unavailable (or a stored matrix failed its integrity check)",
}


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries documenting problem answers of these statuses."""
    return {status: _problem_doc(status) for status in statuses}
