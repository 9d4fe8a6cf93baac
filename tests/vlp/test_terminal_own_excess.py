"""A terminal whose own residual the pooled variances do not explain gets a radius that says
so (``uncertainty.own_excess_widening`` in ``GridlessSolver.solve_terminals``)."""

from __future__ import annotations

import numpy as np
import pytest

from app.vlp.fingerprints import build_fingerprint
from app.vlp.radii import confidence_radius
from app.vlp.solvers.gridless import GridlessSolver
from bench.random_rooms import replay_request


@pytest.mark.parametrize(
    ("room", "trial"),
    [
        (6, 4),  # 16 LEDs, K = 8, realistic mix, 40 dB: one terminal 59 cm off, radius 52 cm
        (6, 9),  # K = 6: one terminal 87 cm off, radius 46 cm
    ],
)
def test_a_terminal_left_far_off_is_not_answered_confidently(room: int, trial: int) -> None:
    # Random rooms (bench/random_rooms.py, seed 3), LEDs' errors weighed: the pooled variances
    # fit the other terminals, and one terminal's fit, far off, left a residual 3.5-4.9x what
    # they predict for it, with a radius as narrow as the others' (about half its error).
    # Wherever the fits land, each terminal is within 0.5 m or its radius is not confident:
    # at least 90 % of its error (a 95 % radius may miss by a little in one case in twenty;
    # the pooled variances move with the other terminals' fits).
    layout, body, truth = replay_request(3, room, trial)
    amplitudes = np.array([terminal["amplitudes"] for terminal in body["terminals"]])
    answer = GridlessSolver(build_fingerprint(layout), "correlation").solve_terminals(amplitudes)
    assert answer.covariances is not None
    errors = np.linalg.norm(answer.positions - truth, axis=1)
    radii = np.array([confidence_radius(covariance) for covariance in answer.covariances])
    assert np.all((errors < 0.5) | (errors <= radii / 0.9)), (errors, radii)
