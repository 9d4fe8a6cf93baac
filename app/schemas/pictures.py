"""Bodies of the picture endpoints (the PNGs themselves are binary answers)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from ._common import FiniteFloat, RequestModel

__all__ = ["LocalizationPlot", "PlotPoint"]


class PlotPoint(BaseModel):
    """A position to draw. Other fields are ignored, so the `estimates` of a localization and
    the `truth` of a simulation can be pasted as they are."""

    model_config = ConfigDict(extra="ignore")

    x: FiniteFloat = Field(description="m")
    y: FiniteFloat = Field(description="m")
    terminal_id: str | None = Field(default=None, max_length=64, description="drawn as a label")


class LocalizationPlot(RequestModel):
    """Estimates (and optionally the true positions) to draw on the room plan."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "estimates": [
                        {"x": 1.02, "y": 1.18, "terminal_id": "t1"},
                        {"x": 2.93, "y": 3.07, "terminal_id": "t2"},
                    ],
                    "truth": [{"x": 1.0, "y": 1.2}, {"x": 2.9, "y": 3.1}],
                }
            ]
        }
    )

    estimates: list[PlotPoint] = Field(max_length=4096, description="estimated positions")
    truth: list[PlotPoint] | None = Field(
        default=None, max_length=4096, description="true positions, matched to the estimates"
    )
    fingerprint_version: int | None = Field(
        default=None, ge=1, description="whose layout to draw; default: the current version"
    )
    width_px: int = Field(default=800, ge=200, le=4000, description="picture width, pixels")
    title: str | None = Field(default=None, max_length=200)
