"""Terminal assignment: estimates labelled with the terminal whose amplitudes they explain."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.assignment import assign_terminals, assignment_costs
from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout
from app.vlp.simulation import noisy_amplitudes, random_positions, true_amplitudes


def test_costs_are_squared_amplitude_errors(paper_room: Layout, rng: np.random.Generator) -> None:
    positions = rng.uniform(0, 4, size=(3, 2))
    amps = rng.uniform(0, 1e-5, size=(2, 16))
    costs = assignment_costs(paper_room, positions, amps)
    predicted = true_amplitudes(paper_room, positions)
    expected = [[float(np.sum((predicted[k] - amps[t]) ** 2)) for t in range(2)] for k in range(3)]
    assert_allclose(costs, expected, rtol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_recovers_a_permutation(paper_room: Layout, seed: int) -> None:
    gen = np.random.default_rng(seed)
    while True:  # targets at least 0.6 m apart, estimates within a few cm
        truth = random_positions(paper_room, 6, rng=gen)
        gaps = np.linalg.norm(truth[:, None] - truth[None], axis=2)
        if gaps[np.triu_indices(6, 1)].min() > 0.6:
            break
    amps = noisy_amplitudes(paper_room, truth, 1e-8, rng=gen)
    order = gen.permutation(6)
    estimates = truth[order] + gen.normal(0, 0.02, size=(6, 2))
    assert_array_equal(assign_terminals(paper_room, estimates, amps), order)


def test_counts_differ(paper_room: Layout) -> None:
    spots = np.array([[0.5, 0.5], [3.5, 3.5], [0.5, 3.5]])
    amps = true_amplitudes(paper_room, spots)
    labels = assign_terminals(paper_room, spots[[2, 0, 1]], amps[[0, 1]])  # 3 est, 2 terminals
    assert_array_equal(labels, [-1, 0, 1])
    fewer = assign_terminals(paper_room, spots[[1]], amps)  # 1 estimate, 3 terminals
    assert_array_equal(fewer, [1])
    assert assign_terminals(paper_room, np.zeros((0, 2)), amps).shape == (0,)


@pytest.mark.parametrize(
    ("positions", "amplitudes", "field"),
    [
        (np.zeros((2, 3)), np.zeros((1, 16)), "positions"),
        (np.zeros((2, 2)), np.zeros((1, 15)), "terminals"),
        (np.zeros((2, 2)), np.full((1, 16), np.nan), "terminals"),
    ],
    ids=["positions-shape", "amplitudes-shape", "nan"],
)
def test_bad_inputs(
    paper_room: Layout, positions: np.ndarray, amplitudes: np.ndarray, field: str
) -> None:
    with pytest.raises(MeasurementError) as info:
        assign_terminals(paper_room, positions, amplitudes)
    assert info.value.field == field
