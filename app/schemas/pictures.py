"""Bodies of the picture endpoints (the PNGs themselves are binary answers)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from .common import MAX_VERSION, FiniteFloat, RequestModel

__all__ = ["MAX_PLOT_M", "LocalizationPlot", "PlotPoint"]

# Positions to draw, metres from the origin at most (far beyond any room; bounded so the
# plot's axis limits stay finite).
MAX_PLOT_M = 1e4


class PlotPoint(BaseModel):
    """A position to draw. Other fields are ignored, so the `estimates` of a localization and
    the `truth` of a simulation can be pasted as they are."""

    model_config = ConfigDict(extra="ignore")

    x: FiniteFloat = Field(ge=-MAX_PLOT_M, le=MAX_PLOT_M, description="m")
    y: FiniteFloat = Field(ge=-MAX_PLOT_M, le=MAX_PLOT_M, description="m")
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
        default=None,
        ge=1,
        le=MAX_VERSION,
        description="whose layout to draw; default: the current version",
    )
    width_px: int = Field(default=800, ge=200, le=4000, description="picture width, pixels")
    title: str | None = Field(default=None, max_length=200)
