"""Pictures of rooms and localization results, rendered to PNG bytes with matplotlib's Agg.

No pyplot: every picture builds its own ``matplotlib.figure.Figure`` and renders it through
``FigureCanvasAgg``, so rendering is thread-safe and leaves no global state behind. Output is
deterministic for the same input (no timestamp or software tag in the PNG).
"""

from __future__ import annotations

from .heatmaps import CrlbMap, HeatmapKind, SampleGrid, amplitude_crlb_m, coverage_counts
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
