"""Every error becomes an RFC 9457 problem (``application/problem+json``).

One place maps the error families (``app.errors``) and the framework's own errors (404, 405,
request validation) to problem answers; handlers raise, they never build error bodies.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.errors import (
    Conflict,
    CorruptMatrix,
    FingerprintNotReady,
    InvalidCursor,
    NotFound,
    PreconditionFailed,
    RegistryError,
    RegistryUnavailable,
    VLPError,
)
from app.schemas import Problem

__all__ = [
    "PROBLEM_MEDIA_TYPE",
    "ApiProblem",
    "InvalidInput",
    "field_location",
    "install_error_handlers",
    "problem_example",
    "problem_response",
    "problem_responses",
]

PROBLEM_MEDIA_TYPE = "application/problem+json"
_TYPE_PREFIX = "urn:vlp:problem:"
_INDEX = re.compile(r"\[(\d+)\]")


class ApiProblem(Exception):
    """An HTTP problem raised by a handler or dependency."""

    def __init__(
        self,
        status: int,
        detail: str,
        *,
        kind: str | None = None,
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
        super().__init__(422, detail, kind="validation", title="Validation failed", errors=errors)


def field_location(field: str | None, prefix: str = "body") -> str:
    """A science-core field (``"leds[3].z"``) as a request location (``"body.leds.3.z"``)."""
    if not field:
        return prefix
    dotted = _INDEX.sub(r".\1", field)
    return f"{prefix}.{dotted}"


def problem_response(
    request: Request,
    status: int,
    detail: str,
    *,
    kind: str | None = None,
    title: str | None = None,
    errors: Iterable[tuple[str, str]] = (),
    headers: Mapping[str, str] | None = None,
) -> JSONResponse:
    """The problem answer for one error."""
    phrase = HTTPStatus(status).phrase if status in HTTPStatus._value2member_map_ else "Error"
    body: dict[str, Any] = {
        "type": f"{_TYPE_PREFIX}{kind}" if kind else "about:blank",
        "title": title or phrase,
        "status": status,
        "detail": detail,
        "instance": request.url.path,
    }
    error_list = [{"field": field, "message": message} for field, message in errors]
    if error_list:
        body["errors"] = error_list
    request_id = getattr(request.state, "request_id", None)
    if request_id:
        body["request_id"] = request_id
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


def _registry_status(exc: RegistryError) -> tuple[int, str]:
    table: tuple[tuple[type[RegistryError], int, str], ...] = (
        (NotFound, 404, "not-found"),
        (PreconditionFailed, 412, "precondition-failed"),
        (FingerprintNotReady, 409, "fingerprint-not-ready"),
        (Conflict, 409, "conflict"),
        (InvalidCursor, 422, "validation"),
        (CorruptMatrix, 503, "corrupt-matrix"),
        (RegistryUnavailable, 503, "registry-unavailable"),
    )
    for cls, status, kind in table:
        if isinstance(exc, cls):
            return status, kind
    return 500, "registry-error"


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


def _allowed_methods(app: FastAPI, path: str) -> str:
    methods: set[str] = set()
    for template, operations in app.openapi().get("paths", {}).items():
        pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template))
        if re.fullmatch(pattern, path):
            methods |= {method.upper() for method in operations}
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
                kind="unsupported-media-type",
                errors=[("header.content-type", unsupported)],
            )
        errors = _validation_errors(exc)
        return problem_response(
            request,
            422,
            f"{len(errors)} invalid input(s): " + "; ".join(f"{f}: {m}" for f, m in errors),
            kind="validation",
            title="Validation failed",
            errors=errors,
        )

    async def on_vlp(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, VLPError)
        errors = [(field_location(exc.field), exc.message)]
        return problem_response(
            request, 422, exc.message, kind="validation", title="Validation failed", errors=errors
        )

    async def on_registry(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RegistryError)
        status, kind = _registry_status(exc)
        errors = [(field_location(exc.field, "query"), exc.message)] if status == 422 else []
        headers = {"Retry-After": "5"} if status == 503 else None
        return problem_response(
            request, status, exc.message, kind=kind, errors=errors, headers=headers
        )

    app.add_exception_handler(ApiProblem, on_api_problem)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(VLPError, on_vlp)
    app.add_exception_handler(RegistryError, on_registry)


# (kind, detail, errors) of a typical answer of each status, as the handlers write them.
_ROOM_ID = "0f3c9a6e5b2d4c1a8e7f6a5b4c3d2e1f"
_EXAMPLES: dict[int, tuple[str, str, list[dict[str, str]]]] = {
    401: ("unauthorized", "this endpoint needs an API key in the X-API-Key header", []),
    403: ("forbidden", "the terminal role may not do this; it needs an admin key", []),
    404: ("not-found", f"no room with id '{_ROOM_ID}'", []),
    409: ("fingerprint-not-ready", f"room {_ROOM_ID} has no ready fingerprint yet", []),
    412: (
        "precondition-failed",
        'If-Match "1" is not the room\'s current ETag "2"; read the room again',
        [],
    ),
    413: ("payload-too-large", "request body larger than 16777216 bytes", []),
    422: (
        "validation",
        "body.grid.step: Input should be greater than 0",
        [{"field": "body.grid.step", "message": "Input should be greater than 0"}],
    ),
    428: ("precondition-required", "send the room's current ETag in If-Match to replace it", []),
    503: ("registry-unavailable", "the registry database is unavailable or busy; try again", []),
}


def problem_example(status: int) -> dict[str, Any]:
    """A problem body of ``status`` as the service answers it (the OpenAPI example).

    A status without an entry in ``_EXAMPLES`` gets a plain one from its description.
    """
    kind, detail, errors = _EXAMPLES.get(status, ("", _DESCRIPTIONS.get(status, ""), []))
    body: dict[str, Any] = {
        "type": f"{_TYPE_PREFIX}{kind}" if kind else "about:blank",
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
