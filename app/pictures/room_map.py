"""The room plan: LEDs, their footprints, the grid and a coverage or CRLB heat map."""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.collections import QuadMesh
from matplotlib.colorbar import Colorbar
from matplotlib.colors import BoundaryNorm, LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FormatStrFormatter, MaxNLocator

from app.vlp.errors import GeometryError
from app.vlp.layout import Layout
from app.vlp.typing import FloatArray

from ._render import draw_grid, draw_leds, draw_room, new_figure, png_bytes
from .heatmaps import (
    MAX_SAMPLES_PER_SIDE,
    CrlbMap,
    HeatmapKind,
    SampleGrid,
    amplitude_crlb_m,
    coverage_counts,
    noise_std_on_samples,
    sample_grid,
)

__all__ = ["resolved_heatmap", "room_map_png"]

_KINDS = ("auto", "coverage", "crlb", "none")
# Coverage maps with at most this many LEDs in view get one discrete colour per count.
_DISCRETE_COVERAGE_LIMIT = 20


def room_map_png(
    layout: Layout,
    *,
    heatmap: HeatmapKind = "auto",
    snr_db: float = 30.0,
    noise_std: float | None = None,
    width_px: int = 800,
    title: str | None = None,
    crlb_map: CrlbMap | None = None,
    max_samples: int = MAX_SAMPLES_PER_SIDE,
) -> bytes:
    """The room plan as PNG bytes.

    Parameters
    ----------
    layout : Layout
    heatmap : {"auto", "coverage", "crlb", "none"}, default="auto"
        ``coverage``: number of LEDs in the receiver's field of view per point;
        ``crlb``: single-target Cramér-Rao bound in cm per point at ``snr_db``;
        ``auto``: ``coverage`` unless every point sees the same number of LEDs (one flat
        colour, as in the paper's room), then ``crlb``.
    snr_db : float, default=30.0
        SNR of the ``crlb`` map, in the service's convention (``app.vlp.simulation``).
    noise_std : float, default=None
        Amplitude noise std for the ``crlb`` map; overrides ``snr_db``. When None it is
        derived from ``snr_db`` with the mean signal power over the heat map's samples (the
        exact grid mean when the grid has at most ``max_samples`` cells per side).
    width_px : int, default=800
        Width of the picture in pixels, in [200, 4000]; the height follows the room.
    title : str, default=None
        Defaults to the room's name and size.
    crlb_map : callable, default=None
        ``(layout, points (P, 2), noise_std) -> bound (P,)`` in metres;
        :func:`app.pictures.heatmaps.amplitude_crlb_m` when None.
    max_samples : int, default=200
        Heat-map samples per side at most (blocks of whole grid cells beyond that).

    Returns
    -------
    png : bytes

    Raises
    ------
    GeometryError
        On an unknown ``heatmap`` (``field="heatmap"``), a non-finite ``snr_db``, a bad
        ``noise_std`` or ``width_px``.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> png = room_map_png(paper_layout(), heatmap="crlb", width_px=300)
    >>> png[:8], int.from_bytes(png[16:20], "big")
    (b'\\x89PNG\\r\\n\\x1a\\n', 300)
    """
    if heatmap not in _KINDS:
        raise GeometryError(f"heatmap must be one of {_KINDS}, got {heatmap!r}", field="heatmap")
    if not np.isfinite(snr_db):
        raise GeometryError(f"snr_db must be finite, got {snr_db!r}", field="snr_db")
    if noise_std is not None and not (np.isfinite(noise_std) and noise_std > 0):
        raise GeometryError(f"noise_std must be positive, got {noise_std!r}", field="noise_std")
    samples = sample_grid(layout, max_samples)
    if heatmap == "auto":
        heatmap = resolved_heatmap(layout, samples)
    # A colour bar beside a long, narrow room would dwarf it: put it below instead.
    below = heatmap != "none" and layout.room.width < 0.6 * layout.room.length
    figure = new_figure(layout, width_px, extra_height=1.2 if below else 0.0)
    axes = figure.add_subplot()
    if heatmap == "coverage":
        _draw_coverage(axes, layout, samples, below=below)
    elif heatmap == "crlb":
        sigma = (
            noise_std
            if noise_std is not None
            else noise_std_on_samples(layout, samples.points, snr_db)
        )
        bound_m = (crlb_map or amplitude_crlb_m)(layout, samples.points, sigma)
        label = f"{snr_db:g} dB SNR" if noise_std is None else f"σ = {noise_std:.3g}"
        _draw_crlb(axes, samples, 100.0 * np.asarray(bound_m), label, below=below)
    has_grid = draw_grid(axes, layout, color="0.55" if heatmap == "none" else "white")
    has_footprints = draw_leds(axes, layout, footprints=True, labels=True)
    draw_room(
        axes, layout, title or _default_title(layout, heatmap, samples, has_grid, has_footprints)
    )
    figure.legend(loc="outside lower center", ncols=4, fontsize="small", frameon=False)
    return png_bytes(figure)


def resolved_heatmap(layout: Layout, samples: SampleGrid) -> HeatmapKind:
    """What ``auto`` draws: ``coverage`` when it varies over the samples, else ``crlb``."""
    counts = coverage_counts(layout, samples.points)
    return "coverage" if counts.size and counts.min() != counts.max() else "crlb"


def _default_title(
    layout: Layout, heatmap: str, samples: SampleGrid, has_grid: bool, has_footprints: bool
) -> str:
    room = layout.room
    name = layout.name or "Room"
    text = (
        f"{name}: {room.length:g} × {room.width:g} × {room.height:g} m, "
        f"{layout.n_leds} LEDs, {layout.n_cells:,} grid points ({layout.grid.step:g} m)"
    )
    notes = []
    if not has_grid:
        notes.append("grid not drawn")
    if not has_footprints:
        notes.append("footprints not drawn")
    if heatmap != "none" and samples.points.shape[0] < layout.n_cells:
        n_y, n_x = samples.shape
        notes.append(f"map on {n_x} × {n_y} blocks")
    return text + (f"\n({'; '.join(notes)})" if notes else "")


def _colorbar(axes: Axes, mesh: QuadMesh, label: str, *, below: bool, extend: str) -> Colorbar:
    figure = axes.get_figure()
    assert isinstance(figure, Figure)
    bar = figure.colorbar(
        mesh,
        ax=axes,
        location="bottom" if below else "right",
        shrink=0.9,
        aspect=40 if below else 20,
        extend=extend,
    )
    bar.set_label(label)
    return bar


def _draw_coverage(axes: Axes, layout: Layout, samples: SampleGrid, *, below: bool) -> None:
    counts = coverage_counts(layout, samples.points).reshape(samples.shape)
    top = max(int(counts.max()), 1)
    if top <= _DISCRETE_COVERAGE_LIMIT:  # one colour per count
        cmap = colormaps["viridis"].resampled(top + 1)
        norm: Normalize = BoundaryNorm(np.arange(-0.5, top + 1.5), cmap.N)
    else:
        cmap, norm = colormaps["viridis"], Normalize(vmin=0.0, vmax=float(top))
    mesh = axes.pcolormesh(
        samples.x_edges,
        samples.y_edges,
        counts,
        cmap=cmap,
        norm=norm,
        shading="flat",
        zorder=1,
        rasterized=True,
    )
    bar = _colorbar(
        axes, mesh, "LEDs in the receiver's field of view", below=below, extend="neither"
    )
    bar.locator = MaxNLocator(integer=True, nbins=min(top + 1, 10))
    bar.update_ticks()


def _draw_crlb(
    axes: Axes, samples: SampleGrid, bound_cm: FloatArray, label: str, *, below: bool
) -> None:
    values = np.ma.masked_invalid(bound_cm.reshape(samples.shape))
    cmap = colormaps["plasma_r"].with_extremes(bad="0.8")
    finite = bound_cm[np.isfinite(bound_cm)]
    if finite.size == 0:
        axes.pcolormesh(
            samples.x_edges,
            samples.y_edges,
            values,
            cmap=cmap,
            shading="flat",
            zorder=1,
            rasterized=True,
        )
    else:
        low = float(finite.min())
        high = max(float(np.percentile(finite, 98)), low * 1.01)
        mesh = axes.pcolormesh(
            samples.x_edges,
            samples.y_edges,
            values,
            cmap=cmap,
            norm=LogNorm(vmin=low, vmax=high),
            shading="flat",
            zorder=1,
            rasterized=True,
        )
        bar = _colorbar(
            axes, mesh, f"single-target CRLB (cm) at {label}", below=below, extend="max"
        )
        axis = bar.ax.xaxis if below else bar.ax.yaxis
        axis.set_major_formatter(FormatStrFormatter("%g"))
        # Label the minor ticks too when the range is under a decade (else no major tick).
        if high < 10.0 * low:
            axis.set_minor_formatter(FormatStrFormatter("%g"))
    if finite.size < bound_cm.size:
        axes.legend(
            handles=[Patch(facecolor="0.8", label="no fix (< 2 LEDs in view)")],
            loc="upper right",
            fontsize="x-small",
            framealpha=0.8,
        )
