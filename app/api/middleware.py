"""Pure ASGI middleware: request ids, access logs, metrics, the 500 guard and the body limit."""

from __future__ import annotations

import contextvars
import json
import logging
import re
import time
import uuid
from http import HTTPStatus
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.telemetry import Metrics

from .errors import PROBLEM_MEDIA_TYPE, ProblemKind

__all__ = ["BodySizeLimitMiddleware", "RequestContextMiddleware", "request_id_var"]

request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "request_id", default=None
)
_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
_access_log = logging.getLogger("app.access")
_error_log = logging.getLogger("app.errors")


async def _send_problem(
    send: Send, scope: Scope, status: int, detail: str, kind: ProblemKind, request_id: str | None
) -> None:
    body: dict[str, Any] = {
        "type": kind.type_uri,
        "title": HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
        "instance": scope.get("path", ""),
    }
    if request_id:
        body["request_id"] = request_id
    payload = json.dumps(body).encode()
    headers = [
        (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
        (b"content-length", str(len(payload)).encode()),
    ]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": payload})


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", []):
        if key.lower() == name:
            return bytes(value).decode("latin-1")
    return None


class RequestContextMiddleware:
    """Request id in and out (``X-Request-ID``), a JSON access log line, request metrics,
    and a problem answer instead of any unhandled exception (logged with the request id)."""

    def __init__(self, app: ASGIApp, *, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = _header(scope, b"x-request-id")
        request_id = incoming if incoming and _REQUEST_ID.match(incoming) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = request_id
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status = 500
        response_started = False

        async def send_wrapper(message: Message) -> None:
            nonlocal status, response_started
            if message["type"] == "http.response.start":
                response_started = True
                status = int(message["status"])
                headers = list(message.get("headers", []))
                headers.append((b"x-request-id", request_id.encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        except Exception:
            _error_log.exception("unhandled error", extra={"request_id": request_id})
            status = 500
            if not response_started:
                await _send_problem(
                    send_wrapper,
                    scope,
                    500,
                    "internal error; quote the request id when reporting it",
                    ProblemKind.INTERNAL,
                    request_id,
                )
        finally:
            elapsed = time.perf_counter() - started
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            method = str(scope.get("method", ""))
            self.metrics.requests.labels(method=method, route=template, status=str(status)).inc()
            self.metrics.latency.labels(method=method, route=template).observe(elapsed)
            _access_log.info(
                "request",
                extra={
                    "request_id": request_id,
                    "method": method,
                    "path": scope.get("path", ""),
                    "route": template,
                    "status": status,
                    "duration_ms": round(elapsed * 1e3, 3),
                },
            )
            request_id_var.reset(token)


class _BodyTooLarge(Exception):
    pass


class BodySizeLimitMiddleware:
    """413 for bodies above ``max_body_bytes``: by ``Content-Length`` and by counting the
    streamed bytes (chunked uploads carry no length)."""

    def __init__(self, app: ASGIApp, *, max_body_bytes: int) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = scope.get("state", {}).get("request_id")
        limit = self.max_body_bytes
        detail = f"request body larger than {limit} bytes"
        declared = _header(scope, b"content-length")
        if declared is not None and not declared.strip().isdigit():
            await _send_problem(
                send,
                scope,
                400,
                "Content-Length is not a number",
                ProblemKind.BAD_REQUEST,
                request_id,
            )
            return
        if declared is not None and int(declared) > limit:
            await _send_problem(send, scope, 413, detail, ProblemKind.PAYLOAD_TOO_LARGE, request_id)
            return
        received = 0
        too_large = False
        started = False

        async def receive_wrapper() -> Message:
            nonlocal received, too_large
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    too_large = True
                    raise _BodyTooLarge
            return message

        async def send_wrapper(message: Message) -> None:
            nonlocal started
            if too_large:
                if message["type"] == "http.response.start" and not started:
                    started = True
                    await _send_problem(
                        send, scope, 413, detail, ProblemKind.PAYLOAD_TOO_LARGE, request_id
                    )
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive_wrapper, send_wrapper)
        except _BodyTooLarge:
            if not started:
                started = True
                await _send_problem(
                    send, scope, 413, detail, ProblemKind.PAYLOAD_TOO_LARGE, request_id
                )
