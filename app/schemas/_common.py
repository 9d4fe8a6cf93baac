"""Shared field types of the public schemas."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["MAX_VERSION", "FiniteFloat", "RequestInt", "RequestModel", "ResponseModel"]

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
