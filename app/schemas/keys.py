"""API keys: create (the secret shown once), list (never the secret), revoke."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import ConfigDict, Field

from .common import RequestModel, ResponseModel

__all__ = ["ApiKey", "ApiKeyCreate", "ApiKeyCreated", "ApiKeysList", "KeyRole", "KeySource"]

KeyRole = Literal["admin", "terminal"]
KeySource = Literal["api", "environment", "generated"]


class ApiKeyCreate(RequestModel):
    """A new key's role and a label to recognise it by (who or what holds it)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"role": "terminal", "label": "lobby kiosk"}]},
    )

    role: KeyRole = Field(description="`admin` may do everything; `terminal` reads and localizes")
    label: str = Field(min_length=1, max_length=200, examples=["terminal of the lobby kiosk"])


class ApiKey(ResponseModel):
    """A key in force, without its secret."""

    id: str
    role: KeyRole
    label: str
    created_at: datetime
    last_used_at: datetime | None = Field(
        description="last use seen by any API process (written at most once a minute per "
        "key and process, so it may lag by that much)"
    )
    source: KeySource = Field(
        description="`api`: made by `POST /v1/keys`, in force until revoked; `environment`: "
        "set in `VLP_ADMIN_KEYS` / `VLP_TERMINAL_KEYS`, in force while set; `generated`: made "
        "at first start, in force while no environment keys are set"
    )


class ApiKeyCreated(ResponseModel):
    """A new key with its secret: shown only in this answer, only its hash is stored."""

    id: str
    role: KeyRole
    label: str
    key: str = Field(description="the secret to send in `X-API-Key`; it cannot be read again")
    created_at: datetime


class ApiKeysList(ResponseModel):
    """The keys in force, oldest first."""

    items: list[ApiKey]
