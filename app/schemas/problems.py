"""RFC 9457 problem details: the body of every error answer."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["FieldError", "Problem"]


class FieldError(BaseModel):
    """One invalid input."""

    field: str = Field(
        description="dotted location, e.g. `body.leds.3.z` or `query.limit`",
        examples=["body.leds.0.z"],
    )
    message: str = Field(examples=["leds[0].z = 5.0 m must be at most room.height (3.0 m)"])


class Problem(BaseModel):
    """An error answer (`application/problem+json`, RFC 9457)."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(
        default="about:blank",
        description="a URI naming the kind of problem",
        examples=["https://vlp.example/problems/validation"],
    )
    title: str = Field(
        description="short summary of the kind of problem", examples=["Validation failed"]
    )
    status: int = Field(ge=400, le=599, examples=[422])
    detail: str = Field(description="what happened in this case", examples=["1 invalid field"])
    instance: str = Field(description="the request path", examples=["/v1/rooms"])
    errors: list[FieldError] | None = Field(
        default=None, description="for validation problems: each invalid field"
    )
    request_id: str | None = Field(default=None, description="quote it when reporting a bug")
