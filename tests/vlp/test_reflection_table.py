"""The reflection table: reproduces diffuse_gains off the nodes, exact gradients, C1, storage."""

from __future__ import annotations

import dataclasses
import io
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.channel import channel_gains
from app.vlp.errors import ProblemSizeError
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Reflectance, Room
from app.vlp.presets import paper_layout
from app.vlp.reflections import ReflectionTable, diffuse_gains

from .conftest import mixed_layout

SURFACES_LIT = Reflectance(walls=0.7, floor=0.2, ceiling=0.8)


def _small_room(height_sd: float = 0.0) -> Layout:
    return Layout(
        room=Room(2.4, 1.8, 2.6, reflectance=SURFACES_LIT),
        grid=Grid(0.2, 0.8, height_sd),
        leds=(Led(0.5, 0.4, 2.6), Led(1.9, 1.3, 2.4, 45.0), Led(1.2, 0.9, 2.6, 70.0)),
        receiver=Receiver(area=1e-4, fov_deg=65.0),
    )


@pytest.fixture(scope="module")
def flat_table() -> ReflectionTable:
    return ReflectionTable.build(_small_room())


@pytest.fixture(scope="module")
def tall_table() -> ReflectionTable:
    return ReflectionTable.build(_small_room(height_sd=0.05))


def _points(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    xs = np.concatenate((rng.uniform(0, 2.4, count), [0.003, 0.07, 2.38, 1.23]))
    ys = np.concatenate((rng.uniform(0, 1.8, count), [0.9, 0.013, 1.79, 0.031]))
    return xs, ys


def test_nodes_cover_the_floor_with_wall_lines(flat_table: ReflectionTable) -> None:
    for nodes, extent in ((flat_table.x_nodes, 2.4), (flat_table.y_nodes, 1.8)):
        assert nodes[0] == 0.0 and nodes[-1] == pytest.approx(extent)
        assert np.max(np.diff(nodes)) <= 0.2 + 1e-12
        assert np.any(np.isclose(nodes, 0.02)) and np.any(np.isclose(nodes, extent - 0.05))
    assert_array_equal(flat_table.z_nodes, [0.8])


def test_interpolant_reproduces_diffuse_gains_off_the_nodes(
    flat_table: ReflectionTable, rng: np.random.Generator
) -> None:
    layout = _small_room()
    xs, ys = _points(rng, 40)
    gains, *_ = flat_table.evaluate(xs, ys)
    exact = diffuse_gains(layout, np.column_stack((xs, ys, np.full(xs.size, 0.8))))
    scale = exact.max(axis=1, keepdims=True)
    # Measured 0.2 % (docs/results/reflections.md).
    assert np.max(np.abs(gains - exact) / scale) < 5e-3


def test_heights_are_interpolated_too(
    tall_table: ReflectionTable, rng: np.random.Generator
) -> None:
    layout = _small_room(height_sd=0.05)
    assert tall_table.z_nodes[0] == pytest.approx(0.65)
    assert tall_table.z_nodes[-1] == pytest.approx(0.95)
    assert tall_table.z_nodes.size >= 4
    xs, ys = _points(rng, 25)
    zs = rng.uniform(0.65, 0.95, xs.size)
    gains, *_ = tall_table.evaluate(xs, ys, zs)
    exact = diffuse_gains(layout, np.column_stack((xs, ys, zs)))
    assert np.max(np.abs(gains - exact) / exact.max(axis=1, keepdims=True)) < 5e-3
    at_default, *_ = tall_table.evaluate(xs, ys)
    assert_allclose(at_default, tall_table.evaluate(xs, ys, np.full(xs.size, 0.8))[0])


@pytest.mark.parametrize("which", ["flat", "tall"])
def test_gradients_are_those_of_the_interpolant(
    which: str,
    flat_table: ReflectionTable,
    tall_table: ReflectionTable,
    rng: np.random.Generator,
) -> None:
    table = flat_table if which == "flat" else tall_table
    xs, ys = _points(rng, 30)
    xs, ys = np.clip(xs, 1e-3, 2.399), np.clip(ys, 1e-3, 1.799)
    zs = rng.uniform(0.66, 0.94, xs.size)
    gains, d_dx, d_dy, d_dz = table.evaluate(xs, ys, zs)
    assert gains.shape == d_dx.shape == d_dy.shape == d_dz.shape == (3, xs.size)
    step = 1e-6
    for coordinate, analytic in enumerate((d_dx, d_dy, d_dz)):
        ahead = [xs.copy(), ys.copy(), zs.copy()]
        behind = [xs.copy(), ys.copy(), zs.copy()]
        ahead[coordinate] += step
        behind[coordinate] -= step
        numeric = (table.evaluate(*ahead)[0] - table.evaluate(*behind)[0]) / (2 * step)
        # (a difference straddling a node sees the jump of the second derivative: C1 only)
        assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-5 * float(np.abs(analytic).max()))
    if which == "flat":
        assert np.all(d_dz == 0)
    else:
        assert np.any(d_dz != 0)


def test_interpolant_is_c1_across_node_lines(flat_table: ReflectionTable) -> None:
    node = flat_table.x_nodes[5]
    ys = np.array([0.33, 1.01])
    below = flat_table.evaluate(np.full(2, node - 1e-9), ys)
    above = flat_table.evaluate(np.full(2, node + 1e-9), ys)
    for left, right in zip(below[:3], above[:3], strict=True):
        assert_allclose(left, right, rtol=1e-6, atol=1e-6 * float(np.abs(right).max()))


def test_points_outside_are_clamped_to_the_room(flat_table: ReflectionTable) -> None:
    outside = flat_table.evaluate(np.array([-0.5, 3.0]), np.array([0.7, 2.5]))
    inside = flat_table.evaluate(np.array([0.0, 2.4]), np.array([0.7, 1.8]))
    assert_allclose(outside[0], inside[0], rtol=1e-12)


def test_round_trip_through_numpy_arrays(
    tall_table: ReflectionTable, rng: np.random.Generator
) -> None:
    buffer = io.BytesIO()
    arrays: dict[str, Any] = dict(tall_table.to_arrays())
    np.savez(buffer, **arrays)
    buffer.seek(0)
    with np.load(buffer) as stored:
        loaded = ReflectionTable.from_arrays(dict(stored))
    xs, ys = _points(rng, 10)
    zs = rng.uniform(0.6, 1.0, xs.size)
    for original, again in zip(
        tall_table.evaluate(xs, ys, zs), loaded.evaluate(xs, ys, zs), strict=True
    ):
        assert_array_equal(original, again)


def test_large_rooms_are_refused_not_exhausted() -> None:
    hall = Layout(
        room=Room(100.0, 100.0, 3.0, reflectance=SURFACES_LIT),
        grid=Grid(0.5, 0.85),
        leds=tuple(Led(1.5 + 3.0 * (i % 32), 1.5 + 3.0 * (i // 32), 3.0) for i in range(1024)),
    )
    with pytest.raises(ProblemSizeError) as info:
        ReflectionTable.build(hall)
    assert info.value.field == "room.reflectance"


# -- fingerprints ------------------------------------------------------------------------


@pytest.mark.parametrize("layout", [mixed_layout(), paper_layout()], ids=["mixed", "paper"])
def test_fingerprint_without_reflectance_is_line_of_sight_bit_for_bit(layout: Layout) -> None:
    fingerprint = build_fingerprint(layout)
    gains = fingerprint.gains
    # every LED at every grid point, independently of the builder's field-of-view discs
    rows = [
        channel_gains(dataclasses.replace(layout, leds=(led,)), layout.cell_centres())[0]
        for led in layout.leds
    ]
    expected = sp.csr_array(np.array(rows))
    expected.sort_indices()
    assert_array_equal(gains.indptr, expected.indptr)
    assert_array_equal(gains.indices, expected.indices)
    assert gains.data.tobytes() == expected.data.tobytes()
    assert fingerprint.reflection_table() is None


def test_fingerprint_with_reflectance_is_the_total_gain() -> None:
    layout = _small_room()
    seen: list[float] = []
    fingerprint = build_fingerprint(layout, progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == pytest.approx(1.0)
    centres = layout.cell_centres()
    los = channel_gains(layout, centres)
    exact = diffuse_gains(layout, np.column_stack((centres, np.full(len(centres), 0.8))))
    total = fingerprint.gains.toarray()
    assert isinstance(fingerprint.gains, sp.csr_array)
    assert np.max(np.abs(total - los - exact) / exact.max(axis=1, keepdims=True)) < 5e-3
    assert fingerprint.reflection_table() is not None
    without = dataclasses.replace(layout, room=dataclasses.replace(layout.room, reflectance=None))
    assert np.all(total >= build_fingerprint(without).gains.toarray())
