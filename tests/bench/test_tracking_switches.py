"""The tracking benchmark's identity switches, counted as the CLEAR MOT metrics count them."""

from __future__ import annotations

import numpy as np

from bench._tracking_runs import correspondences


def _count(truths: list[list[list[float]]], tracks: list[list[list[float]]]) -> int:
    """Switches over instants of two walkers and two tracks (ids 7 and 9)."""
    owner: dict[int, int] = {}
    switches = 0
    ids = np.array([7, 9])
    for truth, tracked in zip(truths, tracks, strict=True):
        now = correspondences(np.array(truth), np.array(tracked), ids, owner)
        switches += sum(1 for w, t in now.items() if w in owner and owner[w] != t)
        owner.update(now)
    return switches


def test_walkers_passing_closer_than_the_tracks_errors_do_not_swap() -> None:
    # Tracks 4 cm off their walkers, walkers 2 cm apart at the middle instant: pairing each
    # instant afresh would hand each walker the other's track there and back again.
    truths = [[[0.0, 0.0], [1.0, 0.0]], [[0.5, 0.0], [0.52, 0.0]], [[1.0, 0.0], [0.0, 0.0]]]
    tracks = [[[0.0, 0.04], [1.0, 0.04]], [[0.54, 0.0], [0.48, 0.0]], [[1.0, 0.04], [0.0, 0.04]]]
    assert _count(truths, tracks) == 0


def test_tracks_that_trade_walkers_count_one_switch_per_walker() -> None:
    truths = [[[0.0, 0.0], [3.0, 0.0]], [[0.0, 0.0], [3.0, 0.0]]]
    tracks = [[[0.0, 0.0], [3.0, 0.0]], [[3.0, 0.0], [0.0, 0.0]]]
    assert _count(truths, tracks) == 2


def test_a_walker_whose_track_is_gone_takes_the_nearest_other() -> None:
    owner = {0: 5}
    now = correspondences(np.array([[0.0, 0.0]]), np.array([[0.1, 0.0]]), np.array([8]), owner)
    assert now == {0: 8}
