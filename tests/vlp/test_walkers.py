"""Simulated walkers: paths at walking speed within the room, crossings, shadowed fixes."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.layout import Layout
from app.vlp.simulation import (
    Impairments,
    crossing_paths,
    random_waypoint_paths,
    simulate_walk,
    true_amplitudes,
)


def test_waypoint_walkers_walk_at_their_speed_inside_the_room(paper_room: Layout) -> None:
    paths = random_waypoint_paths(paper_room, 6, duration_s=60.0, rate_hz=5.0, rng=3)
    assert paths.positions.shape == (300, 6, 2)
    speed = np.linalg.norm(np.diff(paths.positions, axis=0), axis=2) * 5.0
    assert speed.max() <= 1.4 + 1e-9
    standing = ~paths.walking[1:] & ~paths.walking[:-1]
    assert np.all(speed[standing] < 1e-9)
    assert speed[paths.walking[1:] & paths.walking[:-1]].max() > 1.3  # reaches walking speed
    assert paths.positions.min() >= 0.3 - 1e-9 and paths.positions.max() <= 3.7 + 1e-9


def test_crossing_walkers_pass_each_other(paper_room: Layout) -> None:
    paths = crossing_paths(paper_room, duration_s=20.0, rate_hz=5.0, separation_m=0.5)
    gap = np.linalg.norm(paths.positions[:, 0] - paths.positions[:, 1], axis=1)
    assert gap.min() < 0.55
    first = paths.positions[:, 0, 0]
    assert first.min() < 1.0 and first.max() > 3.0


def test_crossing_walkers_speed_up_and_slow_down_as_people_do(paper_room: Layout) -> None:
    paths = crossing_paths(paper_room, duration_s=40.0, rate_hz=5.0, accel_mps2=2.0)
    velocity = np.diff(paths.positions, axis=0) * 5.0  # mean velocity between fixes, m/s
    speed = np.linalg.norm(velocity, axis=2)
    assert speed.max() == pytest.approx(1.4)
    # From standing to walking speed over several fixes, never at once: the mean velocity of
    # successive intervals differs by at most accel * dt.
    change = np.linalg.norm(np.diff(velocity, axis=0), axis=2) * 5.0
    assert change.max() <= 2.0 + 1e-9
    starts = np.nonzero(paths.walking[1:, 0] & ~paths.walking[:-1, 0])[0] + 1
    assert starts.size >= 2
    # The interval after a walk's first fix ends at most 0.4 s into it: at most 0.8 m/s.
    assert np.all(speed[starts, 0] <= 2.0 * 0.4 + 1e-9)


def test_shadowing_blocks_the_strongest_led_of_some_fixes(paper_room: Layout) -> None:
    paths = random_waypoint_paths(paper_room, 4, duration_s=40.0, rate_hz=5.0, rng=5)
    walk = simulate_walk(
        paper_room,
        paths.positions,
        Impairments.ideal(),
        snr_db=float("inf"),
        shadowing_probability=0.05,
        rng=6,
    )
    clean = true_amplitudes(paper_room, paths.positions.reshape(-1, 2)).reshape(
        walk.amplitudes.shape
    )
    shadowed = walk.shadowed
    assert 0.02 < shadowed.mean() < 0.08
    assert_allclose(walk.amplitudes[~shadowed], clean[~shadowed], rtol=1e-12)
    strongest = np.argmax(clean[shadowed], axis=1)
    blocked = walk.amplitudes[shadowed][np.arange(strongest.size), strongest]
    assert np.all(blocked == 0.0)
