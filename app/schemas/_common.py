"""Shared field types of the public schemas."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["FiniteFloat", "RequestModel", "ResponseModel"]

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class RequestModel(BaseModel):
    """Base of request bodies: unknown fields are refused (a typo is a 422, not ignored)."""

    model_config = ConfigDict(extra="forbid")


class ResponseModel(BaseModel):
    """Base of response bodies."""

    model_config = ConfigDict(extra="ignore")
