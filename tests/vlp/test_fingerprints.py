"""Fingerprints: H, J and Psi against a slow double loop over the Lambertian formulas."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
from numpy.testing import assert_allclose

import app.vlp.fingerprints as fingerprints
from app.vlp.channel import channel_gains
from app.vlp.errors import ProblemSizeError
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout

from .conftest import direct_gain


def _slow_matrices(layout: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H, J, Psi by loops over (i, j): grid order j = ix * n_y + iy, rows in triu order."""
    n_leds = layout.n_leds
    step = layout.grid.step
    h = np.zeros((n_leds, layout.n_cells))
    for ix in range(layout.n_x):
        for iy in range(layout.n_y):
            j = ix * layout.n_y + iy
            for i in range(n_leds):
                h[i, j] = direct_gain(layout, i, ((ix + 0.5) * step, (iy + 0.5) * step))
    pilots = [led.pilot_amplitude for led in layout.leds]
    j_matrix = np.array(
        [[(h[i, j] * pilots[i]) ** 2 for j in range(layout.n_cells)] for i in range(n_leds)]
    )
    psi_rows = []
    for i in range(n_leds):
        for l_ in range(i, n_leds):
            psi_rows.append(
                [(h[i, j] * pilots[i]) * (h[l_, j] * pilots[l_]) for j in range(layout.n_cells)]
            )
    return h, j_matrix, np.array(psi_rows)


def test_matrices_match_slow_loop(mixed_room: Layout, mixed_fingerprint: Fingerprint) -> None:
    h, j_matrix, psi = _slow_matrices(mixed_room)
    assert 0.1 < np.mean(h == 0) < 0.9  # genuinely sparse: some LEDs out of view
    assert mixed_fingerprint.n_leds == 5 and mixed_fingerprint.n_cells == 96
    assert_allclose(mixed_fingerprint.gains.toarray(), h, rtol=1e-12, atol=0)
    assert mixed_fingerprint.gains.nnz == np.count_nonzero(h)
    assert_allclose(mixed_fingerprint.dense_gains(), h, rtol=1e-12, atol=0)
    assert_allclose(mixed_fingerprint.power_matrix(), j_matrix, rtol=1e-12, atol=0)
    assert_allclose(mixed_fingerprint.correlation_matrix(), psi, rtol=1e-12, atol=0)
    pilots = mixed_room.pilot_amplitudes
    assert_allclose(mixed_fingerprint.dense_scaled_gains(), pilots[:, None] * h, rtol=1e-12)


def test_sparse_build_equals_dense_computation(
    paper_room: Layout, paper_fingerprint: Fingerprint
) -> None:
    dense = channel_gains(paper_room, paper_room.cell_centres())
    assert_allclose(paper_fingerprint.gains.toarray(), dense, rtol=1e-12, atol=0)


def test_progress_reaches_one(mixed_room: Layout) -> None:
    seen: list[float] = []
    build_fingerprint(mixed_room, progress=seen.append)
    assert len(seen) == mixed_room.n_leds
    assert np.all(np.diff(seen) > 0) and seen[-1] == pytest.approx(1.0)


def test_max_cells(mixed_room: Layout) -> None:
    with pytest.raises(ProblemSizeError) as info:
        build_fingerprint(mixed_room, max_cells=95)
    assert info.value.field == "grid.step"
    assert build_fingerprint(mixed_room, max_cells=96).n_cells == 96


def test_dense_limits(mixed_fingerprint: Fingerprint, monkeypatch: pytest.MonkeyPatch) -> None:
    dense_power = np.asarray(mixed_fingerprint.power_matrix())
    monkeypatch.setattr(fingerprints, "PSI_DENSE_LIMIT", 100)
    with pytest.raises(ProblemSizeError) as info:
        Fingerprint(
            layout=mixed_fingerprint.layout, gains=mixed_fingerprint.gains
        ).correlation_matrix()
    assert info.value.field == "psi"
    monkeypatch.setattr(fingerprints, "DENSE_GAINS_LIMIT", 10)
    fresh = Fingerprint(layout=mixed_fingerprint.layout, gains=mixed_fingerprint.gains)
    assert not fresh.is_dense
    with pytest.raises(ProblemSizeError):
        fresh.dense_gains()
    # the sparse J still equals the dense one
    sparse_power = fresh.power_matrix()
    assert isinstance(sparse_power, sp.csr_array)
    assert_allclose(sparse_power.toarray(), dense_power)


def test_sparse_scaled_gains_share_h_structure_and_keep_no_j(
    mixed_room: Layout, mixed_fingerprint: Fingerprint, monkeypatch: pytest.MonkeyPatch
) -> None:
    h, j_matrix, _ = _slow_matrices(mixed_room)
    monkeypatch.setattr(fingerprints, "DENSE_GAINS_LIMIT", 10)  # the large rooms' path
    fresh = Fingerprint(layout=mixed_room, gains=mixed_fingerprint.gains)
    pilots = mixed_room.pilot_amplitudes
    assert np.ptp(pilots) > 0  # G is not H here
    scaled = fresh.scaled_gains()
    assert_allclose(scaled.toarray(), pilots[:, None] * h, rtol=1e-12, atol=0)
    assert np.shares_memory(scaled.indices, fresh.gains.indices)
    assert np.shares_memory(scaled.indptr, fresh.gains.indptr)
    assert not np.shares_memory(scaled.data, fresh.gains.data)
    by_cell, total = fresh.received_power()
    assert_allclose(by_cell, j_matrix.sum(axis=0), rtol=1e-12, atol=0)
    assert total == pytest.approx(j_matrix.sum(), rel=1e-12)
    # Only the sums are kept: no array as large as J stays with the fingerprint.
    kept = [value for value in fresh._cache.values() if isinstance(value, sp.sparray)]
    assert all(np.shares_memory(matrix.data, scaled.data) for matrix in kept)


def test_scaled_gains_with_unit_pilots_are_h(mixed_room: Layout) -> None:
    unit = dataclasses.replace(
        mixed_room,
        leds=tuple(dataclasses.replace(led, pilot_amplitude=1.0) for led in mixed_room.leds),
    )
    fingerprint = build_fingerprint(unit)
    scaled = fingerprint.scaled_gains()
    assert np.shares_memory(scaled.data, fingerprint.gains.data)
    assert_allclose(scaled.toarray(), fingerprint.gains.toarray(), rtol=0, atol=0)
