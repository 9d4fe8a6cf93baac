"""The localize routes' faster JSON parser gives the standard parser's values and errors."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from starlette.types import Message

from app.api.json_body import _FastJsonRequest

# Valid JSON, and what only the standard parser takes (NaN, a 5000-digit integer) or refuses
# with its own error (broken text, a lone surrogate is fine for it).
BODIES = [
    b'{"power": [1e-9, 2.5e-10, 0.1, 1.7976931348623157e308, 5e-324], "targets": 2}',
    b'{"a": 1, "a": 2, "b": [true, false, null, "\\u00e9\\ud83d\\ude00"]}',
    b'{"x": NaN, "y": -Infinity}',
    b'{"n": ' + b"9" * 5000 + b"}",
    b'{"s": "\\ud800"}',
    b"[" * 3000 + b"]" * 3000,
    b'{"broken": [1, 2',
    b"\xff\xfe not utf-8",
]


async def _parsed(body: bytes) -> Any:
    async def receive() -> Message:
        return {"type": "http.request", "body": body, "more_body": False}

    request = _FastJsonRequest({"type": "http", "method": "POST", "headers": []}, receive)
    return await request.json()


def _standard(body: bytes) -> tuple[str, Any]:
    try:
        return "value", json.loads(body)
    except Exception as exc:  # compare whatever the standard parser raises
        return type(exc).__name__, str(exc)


@pytest.mark.parametrize("body", BODIES, ids=range(len(BODIES)))
def test_same_value_or_error_as_the_standard_parser(body: bytes) -> None:
    kind, expected = _standard(body)
    if kind == "value":
        got = asyncio.run(_parsed(body))
        assert json.dumps(got) == json.dumps(expected)  # NaN-safe and type-exact
        return
    with pytest.raises(Exception) as raised:
        asyncio.run(_parsed(body))
    assert (type(raised.value).__name__, str(raised.value)) == (kind, expected)
