"""Shared field types of the public schemas."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field
from pydantic.config import JsonDict

__all__ = [
    "MAX_VERSION",
    "FiniteFloat",
    "RequestInt",
    "RequestModel",
    "ResponseModel",
    "lazy_examples",
]

# Strict: a JSON number only (an integer is fine), never `true` or `"1.5"`, which lax
# parsing would turn into 1.0 and 1.5 behind the caller's back; NaN and Infinity refused.
FiniteFloat = Annotated[float, Field(allow_inf_nan=False, strict=True)]
# Strict: a JSON integer only, never `true`, `2.0` or `"2"`.
RequestInt = Annotated[int, Field(strict=True)]
# Versions are 64-bit integers in the registry; larger numbers cannot name one.
MAX_VERSION = 10**18 - 1


class RequestModel(BaseModel):
    """Base of request bodies: unknown fields are refused (a typo is a 422, not ignored)."""

    model_config = ConfigDict(extra="forbid")


class ResponseModel(BaseModel):
    """Base of response bodies."""

    model_config = ConfigDict(extra="ignore")


def lazy_examples(*factories: Callable[[], dict[str, Any]]) -> Callable[[JsonDict], None]:
    """A ``json_schema_extra`` whose ``examples`` are computed when the schema is generated.

    Some examples are computed by the science core (noiseless amplitudes in the paper room);
    computing them at import would load numpy into every client of these schemas.
    """

    def add_examples(schema: JsonDict) -> None:
        schema["examples"] = [factory() for factory in factories]

    return add_examples
