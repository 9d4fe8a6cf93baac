"""Tests of app/pictures/heatmaps.py against independent computations."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from app.pictures.heatmaps import (
    amplitude_crlb_m,
    coverage_counts,
    noise_std_on_samples,
    sample_grid,
)
from app.vlp.channel import channel_gains
from app.vlp.crlb import single_target_crlb
from app.vlp.fingerprints import Fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.simulation import noise_std_for_snr
from app.vlp.typing import FloatArray


def _hall() -> Layout:
    leds = (Led(1.5, 1.5, 3.0, 45.0), Led(5.0, 1.5, 2.8, 60.0, 1.3), Led(8.5, 4.5, 3.0, 50.0))
    return Layout(Room(10.0, 6.0, 3.0), Grid(0.5, 0.85), leds, Receiver(fov_deg=50.0))


def test_small_grid_samples_are_the_grid_points(paper_room: Layout) -> None:
    samples = sample_grid(paper_room)
    assert samples.shape == (paper_room.n_y, paper_room.n_x)
    got = {tuple(np.round(p, 9)) for p in samples.points}
    want = {tuple(np.round(p, 9)) for p in paper_room.cell_centres()}
    assert got == want


def test_large_grid_is_decimated_into_whole_cell_blocks() -> None:
    layout = Layout(Room(100.0, 30.0, 4.0), Grid(0.1, 0.85), (Led(50.0, 15.0, 4.0),))
    samples = sample_grid(layout, 200)
    n_y, n_x = samples.shape
    assert n_x <= 200 and n_y <= 200 and n_x * n_y == samples.points.shape[0]
    assert samples.x_edges[0] == 0.0 and samples.x_edges[-1] == pytest.approx(100.0)
    assert samples.y_edges[-1] == pytest.approx(30.0)
    cells = samples.x_edges / layout.grid.step
    np.testing.assert_allclose(cells, np.round(cells), atol=1e-9)
    # Row-major over (y, x): the second point moves along x.
    assert samples.points[1, 1] == samples.points[0, 1]
    assert samples.points[1, 0] > samples.points[0, 0]


def test_coverage_counts_match_the_fov_discs() -> None:
    layout = _hall()
    points = np.random.default_rng(5).uniform((0, 0), (10, 6), size=(2000, 2))
    heights = layout.led_positions[:, 2] - layout.grid.receiver_height
    radius = heights * math.tan(math.radians(layout.receiver.fov_deg))
    distance = np.linalg.norm(points[None, :, :] - layout.led_positions[:, None, :2], axis=2)
    np.testing.assert_array_equal(
        coverage_counts(layout, points), (distance <= radius[:, None]).sum(axis=0)
    )


def test_noise_on_the_full_grid_matches_the_service_convention(
    paper_room: Layout, paper_fingerprint: Fingerprint
) -> None:
    samples = sample_grid(paper_room)
    for snr_db in (20.0, 30.0):
        assert noise_std_on_samples(paper_room, samples.points, snr_db) == pytest.approx(
            noise_std_for_snr(paper_fingerprint, snr_db), rel=1e-12
        )


def _numeric_crlb(layout: Layout, point: FloatArray, noise_std: float) -> float:
    """sqrt(trace(F^-1)) with a central-difference Jacobian of the amplitudes."""
    delta = 1e-6
    columns = []
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = delta
        up = channel_gains(layout, (point + step)[None])[:, 0]
        down = channel_gains(layout, (point - step)[None])[:, 0]
        columns.append(layout.pilot_amplitudes * (up - down) / (2 * delta))
    jacobian = np.column_stack(columns)
    fisher = jacobian.T @ jacobian / noise_std**2
    return float(np.sqrt(np.trace(np.linalg.inv(fisher))))


def test_crlb_matches_a_numeric_fisher_matrix() -> None:
    layout = replace(_hall(), receiver=Receiver(fov_deg=80.0))
    points = np.array([[2.0, 2.0], [4.3, 3.1], [7.7, 0.9], [9.0, 5.5]])
    got = amplitude_crlb_m(layout, points, 2e-7)
    want = [_numeric_crlb(layout, p, 2e-7) for p in points]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # Linear in the noise std.
    np.testing.assert_allclose(amplitude_crlb_m(layout, points, 4e-7), 2 * got, rtol=1e-12)


@pytest.mark.parametrize("room", ["paper", "hall"])
def test_crlb_agrees_with_the_science_core_bound(paper_room: Layout, room: str) -> None:
    layout = paper_room if room == "paper" else _hall()
    points = sample_grid(layout).points
    got = amplitude_crlb_m(layout, points, 3e-7)
    want = np.array([single_target_crlb(layout, p, 3e-7) for p in points])
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    finite = np.isfinite(want)
    assert finite.sum() > 0.5 * finite.size if room == "paper" else finite.sum() > 10
    np.testing.assert_allclose(got[finite], want[finite], rtol=1e-10)


def test_crlb_is_infinite_without_two_leds_in_view() -> None:
    layout = _hall()
    # (1.5, 3.5) sees LED 0 only; (9.5, 0.2) sees none; (3.25, 1.5) sees LEDs 0 and 1 on the
    # line through both, where the y coordinate is unobservable.
    points = np.array([[1.5, 3.5], [9.5, 0.2], [3.25, 1.5], [3.25, 2.0]])
    bound = amplitude_crlb_m(layout, points, 1e-7)
    assert np.isinf(bound[:3]).all()
    assert np.isfinite(bound[3])
