"""Shared drawing functions: figures sized in pixels, PNG bytes, the room outline and its LEDs."""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PatchCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from app.vlp.errors import GeometryError
from app.vlp.layout import Layout

__all__ = [
    "DPI",
    "FOOTPRINT_LIMIT",
    "GRID_DRAW_LIMIT",
    "LABEL_LIMIT",
    "draw_grid",
    "draw_leds",
    "draw_room",
    "new_figure",
    "png_bytes",
]

DPI = 100
# Grids with more cells than this are not drawn cell by cell.
GRID_DRAW_LIMIT = 10_000
# Rooms with more LEDs than this get no index labels (they would overlap) ...
LABEL_LIMIT = 64
# ... and no footprints (hundreds of overlapping circles hide the heat map).
FOOTPRINT_LIMIT = 36
_MIN_WIDTH_PX, _MAX_WIDTH_PX = 200, 4000


def new_figure(layout: Layout, width_px: int, *, extra_height: float = 0.0) -> Figure:
    """A figure ``width_px`` wide whose height follows the room's aspect ratio.

    Raises
    ------
    GeometryError
        When ``width_px`` is outside [200, 4000] (``field="width_px"``).
    """
    if not _MIN_WIDTH_PX <= width_px <= _MAX_WIDTH_PX:
        raise GeometryError(
            f"width_px must be in [{_MIN_WIDTH_PX}, {_MAX_WIDTH_PX}], got {width_px!r}",
            field="width_px",
        )
    aspect = layout.room.width / layout.room.length
    width_in = width_px / DPI
    height_in = min(
        max(width_in * 0.8 * aspect + 1.1 + extra_height, 0.3 * width_in), 1.6 * width_in
    )
    # Whole pixels, so the PNG is exactly width_px wide.
    height_in = math.ceil(height_in * DPI) / DPI
    return Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")


def png_bytes(figure: Figure) -> bytes:
    """Render a figure to PNG bytes (Agg), without a timestamp or software tag."""
    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # A title or label with a character the font lacks is drawn with a box; the warning
        # says so and must not fail the picture.
        warnings.filterwarnings(
            "ignore", message=r"Glyph .* missing from font", category=UserWarning
        )
        figure.savefig(buffer, format="png", dpi=DPI, metadata={"Software": None})
    return buffer.getvalue()


def draw_room(axes: Axes, layout: Layout, title: str) -> None:
    """Room outline, metre axes, equal aspect, a small margin and the title."""
    length, width = layout.room.length, layout.room.width
    axes.add_patch(
        Rectangle((0.0, 0.0), length, width, fill=False, edgecolor="0.2", linewidth=1.2, zorder=4)
    )
    margin = 0.03 * max(length, width)
    axes.set_xlim(-margin, length + margin)
    axes.set_ylim(-margin, width + margin)
    axes.set_aspect("equal")
    axes.set_xlabel("x (m)")
    axes.set_ylabel("y (m)")
    axes.set_title(title, fontsize="medium")


def draw_grid(axes: Axes, layout: Layout, *, color: str = "0.55") -> bool:
    """Grid-point centres as small dots, unless there are more than :data:`GRID_DRAW_LIMIT`."""
    if layout.n_cells > GRID_DRAW_LIMIT:
        return False
    centres = layout.cell_centres()
    size = float(np.clip(2000.0 / layout.n_cells, 0.3, 4.0))
    axes.scatter(centres[:, 0], centres[:, 1], s=size, c=color, marker=".", linewidths=0, zorder=2)
    return True


def draw_leds(axes: Axes, layout: Layout, *, footprints: bool, labels: bool) -> bool:
    """LED markers with their indices; optionally the FOV and half-power footprints.

    Labels are left out above :data:`LABEL_LIMIT` LEDs, footprints above
    :data:`FOOTPRINT_LIMIT`; returns whether footprints were drawn.

    On the receivers' plane an LED at height ``dz`` above it is seen within the receiver's
    field of view inside a circle of radius ``dz tan(FOV)``; its half-power footprint (where
    the irradiance angle equals the half-power angle) has radius ``dz tan(half-power)``.
    """
    positions = layout.led_positions
    footprints = footprints and layout.n_leds <= FOOTPRINT_LIMIT
    if footprints:
        heights = positions[:, 2] - layout.grid.receiver_height
        fov = math.radians(min(layout.receiver.fov_deg, 89.9))
        half = np.deg2rad(layout.half_power_angles_deg)
        fov_discs = [
            Circle((x, y), dz * math.tan(fov))
            for (x, y), dz in zip(positions[:, :2], heights, strict=True)
        ]
        half_discs = [
            Circle((x, y), dz * math.tan(a))
            for (x, y), dz, a in zip(positions[:, :2], heights, half, strict=True)
        ]
        room = Rectangle(
            (0.0, 0.0), layout.room.length, layout.room.width, transform=axes.transData
        )
        for discs, colour, style in ((fov_discs, "0.25", "--"), (half_discs, "tab:orange", "-")):
            collection = PatchCollection(
                discs,
                facecolor="none",
                edgecolor=colour,
                linestyle=style,
                linewidth=0.7,
                alpha=0.8,
                zorder=3,
            )
            axes.add_collection(collection)
            collection.set_clip_path(room)  # footprints only inside the room
        axes.plot(
            [],
            [],
            color="0.25",
            linestyle="--",
            linewidth=0.7,
            label=f"FOV footprint ({layout.receiver.fov_deg:g}°)",
        )
        axes.plot(
            [],
            [],
            color="tab:orange",
            linewidth=0.7,
            label=f"half-power footprint ({_angles_text(layout)})",
        )
    size = 60.0 if layout.n_leds <= LABEL_LIMIT else 20.0
    axes.scatter(
        positions[:, 0],
        positions[:, 1],
        s=size,
        marker="o",
        c="gold",
        edgecolors="black",
        linewidths=0.8,
        zorder=5,
        label="LED",
    )
    if labels and layout.n_leds <= LABEL_LIMIT:
        offset = 0.012 * max(layout.room.length, layout.room.width)
        for index, (x, y) in enumerate(positions[:, :2]):
            axes.annotate(
                str(index),
                (x + offset, y + offset),
                fontsize="x-small",
                zorder=6,
                color="black",
                bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7},
            )
    return footprints


def _angles_text(layout: Layout) -> str:
    low, high = float(layout.half_power_angles_deg.min()), float(layout.half_power_angles_deg.max())
    return f"{low:.3g}°" if high - low < 0.05 else f"{low:.3g}°–{high:.3g}°"
