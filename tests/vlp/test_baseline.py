"""RSS baseline: exact without noise, sensible with noise, robust at the edges."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.baseline import rss_localize
from app.vlp.errors import MeasurementError
from app.vlp.layout import Layout
from app.vlp.simulation import noisy_amplitudes, random_positions, true_amplitudes


def test_exact_without_noise(paper_room: Layout, rng: np.random.Generator) -> None:
    truth = random_positions(paper_room, 50, distinct_cells=False, rng=rng)
    estimates = rss_localize(paper_room, true_amplitudes(paper_room, truth))
    assert estimates.shape == (50, 2)
    assert_allclose(estimates, truth, atol=1e-8)


def test_exact_in_a_sparse_room(mixed_room: Layout, rng: np.random.Generator) -> None:
    """Different LED heights, beams and pilots; narrow FOV (some LEDs unseen)."""
    truth = rng.uniform(0.6, 1.0, size=(20, 2)) * [2.0, 1.2]
    amps = true_amplitudes(mixed_room, truth)
    seen = (amps > 0).sum(axis=1)
    estimates = rss_localize(mixed_room, amps)
    good = seen >= 3
    assert good.sum() >= 5
    assert_allclose(estimates[good], truth[good], atol=1e-6)


def test_corners_and_walls(paper_room: Layout) -> None:
    truth = np.array([[0.0, 0.0], [4.0, 4.0], [0.0, 4.0], [2.0, 0.0]])
    estimates = rss_localize(paper_room, true_amplitudes(paper_room, truth))
    assert_allclose(estimates, truth, atol=1e-6)


def test_noise_gives_small_errors_inside_the_room(
    paper_room: Layout, rng: np.random.Generator
) -> None:
    truth = random_positions(paper_room, 100, distinct_cells=False, rng=rng)
    clean = true_amplitudes(paper_room, truth)
    amps = noisy_amplitudes(paper_room, truth, 0.01 * float(np.mean(clean)), rng=rng)
    estimates = rss_localize(paper_room, amps)
    errors = np.linalg.norm(estimates - truth, axis=1)
    assert np.all((estimates >= 0) & (estimates <= 4.0))
    assert np.mean(errors) < 0.05
    assert np.max(errors) < 0.5


def test_weak_signal_falls_back_to_strongest_led(paper_room: Layout) -> None:
    amps = np.zeros((1, 16))
    amps[0, 5] = 1e-6  # only one LED heard
    estimate = rss_localize(paper_room, amps)
    assert estimate.shape == (1, 2)
    assert np.all((estimate >= 0) & (estimate <= 4))
    single = rss_localize(paper_room, true_amplitudes(paper_room, np.array([[1.0, 2.0]]))[0])
    assert_allclose(single, [[1.0, 2.0]], atol=1e-8)  # a 1-D row is one terminal


@pytest.mark.parametrize("bad", [np.zeros((2, 15)), np.full((1, 16), np.inf)], ids=["shape", "inf"])
def test_bad_inputs(paper_room: Layout, bad: np.ndarray) -> None:
    with pytest.raises(MeasurementError) as info:
        rss_localize(paper_room, bad)
    assert info.value.field == "amplitudes"
