"""Tests of app/pictures/room_map.py: valid, deterministic PNGs that show what they should."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from matplotlib.figure import Figure

import app.pictures.room_map
from app.pictures import HeatmapKind, room_map_png
from app.pictures._render import draw_leds
from app.pictures.heatmaps import (
    MAX_SAMPLES_PER_SIDE,
    amplitude_crlb_m,
    coverage_counts,
    noise_std_on_samples,
    sample_grid,
)
from app.pictures.room_map import resolved_heatmap
from app.vlp.errors import GeometryError
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.typing import FloatArray, IntArray

from .conftest import decode, png_size


def _hall() -> Layout:
    leds = tuple(
        Led(x, y, 3.0, 45.0 if (x + y) % 2 else 60.0) for x in (1.5, 5.0, 8.5) for y in (1.5, 4.5)
    )
    return Layout(Room(10.0, 6.0, 3.0), Grid(0.1, 0.85), leds, Receiver(fov_deg=50.0), name="Hall")


@pytest.mark.parametrize("heatmap", ["coverage", "crlb", "none"])
@pytest.mark.parametrize("width_px", [400, 800])
def test_png_is_valid_and_as_wide_as_asked(paper_room: Layout, heatmap: str, width_px: int) -> None:
    png = room_map_png(paper_room, heatmap=heatmap, width_px=width_px)  # type: ignore[arg-type]
    width, height = png_size(png)
    assert width == width_px
    assert 0.3 * width_px <= height <= 1.6 * width_px
    assert decode(png).shape[:2] == (height, width)


def test_output_is_deterministic(paper_room: Layout) -> None:
    first = room_map_png(paper_room, heatmap="crlb")
    assert room_map_png(paper_room, heatmap="crlb") == first
    assert b"Software" not in first and b"matplotlib" not in first


def test_heat_maps_give_different_pictures(paper_room: Layout) -> None:
    pictures = {
        kind: decode(room_map_png(paper_room, heatmap=kind))
        for kind in ("coverage", "crlb", "none")
    }
    for a, b in (("coverage", "crlb"), ("coverage", "none"), ("crlb", "none")):
        assert pictures[a].shape == pictures[b].shape
        assert np.abs(pictures[a] - pictures[b]).mean() > 0.01


def _grey_fraction(pixels: FloatArray, level: float) -> float:
    rgb = pixels[:, :, :3]
    return float(np.mean(np.all(np.abs(rgb - level) < 0.01, axis=2)))


def test_crlb_map_shows_no_fix_regions_in_grey() -> None:
    """Where fewer than two LEDs are in view the bound is infinite and drawn light grey."""
    hall = _hall()
    assert _grey_fraction(decode(room_map_png(hall, heatmap="crlb")), 0.8) > 0.05
    assert _grey_fraction(decode(room_map_png(hall, heatmap="coverage")), 0.8) < 0.01


def test_injected_crlb_map_receives_samples_and_noise(paper_room: Layout) -> None:
    calls: list[tuple[int, float]] = []

    def constant(layout: Layout, points: FloatArray, noise_std: float) -> FloatArray:
        assert layout is paper_room
        calls.append((points.shape[0], noise_std))
        return np.full(points.shape[0], 0.05) + 0.01 * points[:, 0]

    png = room_map_png(paper_room, heatmap="crlb", snr_db=20.0, crlb_map=constant)
    samples = sample_grid(paper_room)
    assert len(calls) == 1 and calls[0][0] == paper_room.n_cells
    assert calls[0][1] == pytest.approx(noise_std_on_samples(paper_room, samples.points, 20.0))
    assert png != room_map_png(paper_room, heatmap="crlb", snr_db=20.0)
    room_map_png(paper_room, heatmap="crlb", noise_std=3e-7, crlb_map=constant)
    assert calls[-1] == (paper_room.n_cells, 3e-7)


def test_million_point_room_is_drawn_from_a_bounded_sample(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 10^6-point room costs what a 200 x 200 one does: each heat map is evaluated on at
    most MAX_SAMPLES_PER_SIDE^2 block centres, and no array of every grid point is made.
    (Render times: ``python -m bench.bounded_work``, docs/results/bounded-work.md.)"""
    leds = tuple(Led(x, y, 4.0) for x in (20.0, 50.0, 80.0) for y in (25.0, 75.0))
    big = Layout(Room(100.0, 100.0, 4.0), Grid(0.1, 0.85), leds, name="Big")
    assert big.n_cells == 1_000_000
    evaluated: list[int] = []
    centred: list[int] = []

    def counted_coverage(layout: Layout, points: FloatArray) -> IntArray:
        evaluated.append(points.shape[0])
        return coverage_counts(layout, points)

    def counted_crlb(layout: Layout, points: FloatArray, noise_std: float) -> FloatArray:
        evaluated.append(points.shape[0])
        return amplitude_crlb_m(layout, points, noise_std)

    cell_centres = Layout.cell_centres

    def counted_centres(layout: Layout, indices: IntArray | None = None) -> FloatArray:
        centres = cell_centres(layout, indices)
        centred.append(centres.shape[0])
        return centres

    monkeypatch.setattr(app.pictures.room_map, "coverage_counts", counted_coverage)
    monkeypatch.setattr(Layout, "cell_centres", counted_centres)
    for heatmap in ("coverage", "crlb"):
        png = room_map_png(big, heatmap=heatmap, width_px=600, crlb_map=counted_crlb)
        assert png_size(png)[0] == 600
    assert evaluated == [MAX_SAMPLES_PER_SIDE**2] * 2
    assert max(centred, default=0) <= MAX_SAMPLES_PER_SIDE**2


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"heatmap": "power"}, "heatmap"),
        ({"width_px": 50}, "width_px"),
        ({"width_px": 10_000}, "width_px"),
        ({"snr_db": float("nan")}, "snr_db"),
        ({"noise_std": -1.0}, "noise_std"),
        ({"noise_std": 0.0}, "noise_std"),
    ],
    ids=["heatmap", "narrow", "wide", "snr-nan", "noise-negative", "noise-zero"],
)
def test_bad_options_raise_with_field(
    paper_room: Layout, kwargs: dict[str, object], field: str
) -> None:
    with pytest.raises(GeometryError) as info:
        room_map_png(paper_room, **kwargs)  # type: ignore[arg-type]
    assert info.value.field == field


def test_concurrent_rendering_matches_serial(paper_room: Layout) -> None:
    """No pyplot state: pictures rendered in threads are byte-identical to serial ones."""
    kinds: list[HeatmapKind] = ["coverage", "crlb", "none", "coverage"]
    serial = [room_map_png(paper_room, heatmap=kind, width_px=400) for kind in kinds]
    with ThreadPoolExecutor(max_workers=4) as pool:
        threaded = list(
            pool.map(lambda k: room_map_png(paper_room, heatmap=k, width_px=400), kinds)
        )
    assert threaded == serial


@pytest.mark.parametrize("heatmap", ["coverage", "crlb"])
def test_long_narrow_room_puts_the_colour_bar_below(heatmap: HeatmapKind) -> None:
    """The picture of a 40 x 3 m corridor is wide and flat, not mostly empty."""
    leds = tuple(Led(x, 1.5, 3.0) for x in np.arange(2.0, 40.0, 4.0))
    corridor = Layout(Room(40.0, 3.0, 3.0), Grid(0.25, 0.85), leds, name="Corridor")
    width, height = png_size(room_map_png(corridor, heatmap=heatmap, width_px=800))
    assert width == 800 and height < 0.45 * width


@pytest.mark.parametrize(
    ("n_side", "footprints", "labels"), [(6, True, True), (7, False, True), (9, False, False)]
)
def test_dense_ceilings_skip_footprints_then_labels(
    n_side: int, footprints: bool, labels: bool
) -> None:
    ticks = np.arange(n_side) + 0.5
    leds = tuple(Led(float(x), float(y), 4.0) for x in ticks for y in ticks)
    room = Layout(Room(float(n_side), float(n_side), 4.0), Grid(0.5, 0.85), leds)
    axes = Figure().add_subplot()
    assert draw_leds(axes, room, footprints=True, labels=True) is footprints
    assert len(axes.collections) == (3 if footprints else 1)  # FOV, half-power, markers
    assert len(axes.texts) == (room.n_leds if labels else 0)


def test_auto_heatmap_draws_coverage_only_when_it_varies(paper_room: Layout) -> None:
    samples = sample_grid(paper_room, 50)
    # Every point of the paper room sees all 16 LEDs: a flat coverage map.
    assert resolved_heatmap(paper_room, samples) == "crlb"
    narrow = replace(paper_room, receiver=replace(paper_room.receiver, fov_deg=30.0))
    assert resolved_heatmap(narrow, sample_grid(narrow, 50)) == "coverage"
    assert room_map_png(paper_room, width_px=300) == room_map_png(
        paper_room, heatmap="crlb", width_px=300
    )
