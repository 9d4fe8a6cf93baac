"""Pictures of rooms and localization results, rendered to PNG bytes with matplotlib's Agg.

No pyplot: every picture builds its own ``matplotlib.figure.Figure`` and renders it through
``FigureCanvasAgg``, so rendering is thread-safe and leaves no global state behind. Output is
deterministic for the same input (no timestamp or software tag in the PNG).

The renderers (``localization_png``, ``room_map_png``) load matplotlib when first asked for:
an API process that never draws (the heat maps' numbers alone serve the tracks' accuracy
map) does not hold it.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

from .heatmaps import CrlbMap, HeatmapKind, SampleGrid, amplitude_crlb_m, coverage_counts

if TYPE_CHECKING:
    from .localization import localization_png
    from .room_map import room_map_png

__all__ = [
    "CrlbMap",
    "HeatmapKind",
    "SampleGrid",
    "amplitude_crlb_m",
    "coverage_counts",
    "localization_png",
    "room_map_png",
]

# The renderers and their modules, imported on first use (they import matplotlib).
_RENDERERS = {"localization_png": ".localization", "room_map_png": ".room_map"}


def __getattr__(name: str) -> Any:
    """The renderers, imported when first asked for (PEP 562)."""
    module = _RENDERERS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(module, __name__), name)
    globals()[name] = value
    return value
