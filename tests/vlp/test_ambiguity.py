"""Mirror twins (app/vlp/ambiguity.py) and the answers that carry them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy import optimize, stats

from app.vlp.ambiguity import (
    covering_twins,
    far_optima,
    farthest_in_region,
    mirror_twins,
    reaching_beyond,
    twins_possible,
)
from app.vlp.channel import channel_gains
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Room
from app.vlp.radii import confidence_radii
from app.vlp.simulation import Impairments, random_positions, simulate_terminals
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.typing import FloatArray


def corridor(row_y: float = 1.0) -> Layout:
    """A 6 x 2.5 m corridor lit by one row of four LEDs at ``y = row_y``."""
    return Layout(
        room=Room(6.0, 2.5, 3.0),
        grid=Grid(0.1, 0.85),
        leds=tuple(Led(x=0.75 + 1.5 * i, y=row_y, z=3.0) for i in range(4)),
    )


def gains_of(layout: Layout) -> Callable[[FloatArray], FloatArray]:
    """The paper's channel at the receivers' plane: an independent evaluation."""
    return lambda points: channel_gains(layout, points)


def led_xy(layout: Layout) -> FloatArray:
    return np.array([(led.x, led.y) for led in layout.leds])


def test_a_single_row_of_leds_gives_every_point_its_mirror_image() -> None:
    layout = corridor()
    points = np.array([[1.2, 0.3], [4.0, 1.6], [2.9, 0.95]])
    twins = mirror_twins(points, led_xy(layout), gains_of(layout), (6.0, 2.5))
    np.testing.assert_allclose(twins, [[1.2, 1.7], [4.0, 0.4], [2.9, 1.05]], atol=1e-12)
    # The same line-of-sight gains on both sides (distances and angles are mirrored).
    np.testing.assert_allclose(
        channel_gains(layout, twins), channel_gains(layout, points), rtol=1e-12
    )


def test_no_twin_outside_the_room_or_among_leds_off_one_line(
    paper_fingerprint: Fingerprint,
) -> None:
    layout = corridor(row_y=0.8)
    # 0.3 m below the row is 0.5 m; its mirror at 2.3 m is inside, 0.2 m is outside.
    twins = mirror_twins(
        np.array([[3.0, 0.5], [3.0, 2.4]]), led_xy(layout), gains_of(layout), (6.0, 2.5)
    )
    np.testing.assert_allclose(twins[0], [3.0, 1.1], atol=1e-12)
    assert np.isnan(twins[1]).all()
    # The paper room's 4 x 4 array: the mirror image across any line receives other gains.
    paper = paper_fingerprint.layout
    points = random_positions(paper, 200, rng=np.random.default_rng(3))
    twins = mirror_twins(points, led_xy(paper), gains_of(paper), (4.0, 4.0))
    assert np.isnan(twins).all()


def test_the_widened_region_holds_the_twin() -> None:
    positions = np.array([[1.0, 0.5], [2.0, 2.0], [3.0, 1.0]])
    twins = np.array([[1.0, 1.5], [np.nan, np.nan], [3.0, 1.2]])
    tight = np.repeat(np.eye(2)[np.newaxis] * 1e-4, 3, axis=0)  # 2.4 cm radii
    widened = covering_twins(tight, positions, twins)
    radii = confidence_radii(widened)
    distance = np.linalg.norm(twins - positions, axis=1)
    assert radii[0] > 1.3 * distance[0] and radii[2] > 1.3 * distance[2]
    np.testing.assert_array_equal(widened[1], tight[1])
    # Widened along the step only: across it the variance is the same.
    assert widened[0, 0, 0] == pytest.approx(1e-4) and widened[0, 0, 1] == 0.0


def test_answers_in_a_single_row_corridor_hold_the_mirror_image() -> None:
    """Terminals in a corridor with one row of LEDs, their own amplitudes (ideal model,
    40 dB): the fit lands on either side of the row, and every 95 % circle holds the truth
    (before: radii of a few centimetres, truth on the other side, quality `ok`)."""
    layout = corridor()
    fingerprint = build_fingerprint(layout)
    solver = GridlessSolver(fingerprint, "correlation")
    rng = np.random.default_rng(11)
    truth = np.column_stack((rng.uniform(0.3, 5.7, 12), rng.uniform(0.1, 2.4, 12)))
    simulated = simulate_terminals(layout, truth, Impairments.ideal(), snr_db=40.0, rng=rng)
    solution = solver.solve_terminals(simulated.amplitudes)
    assert solution.covariances is not None and solution.fit is not None
    errors = np.linalg.norm(solution.positions - truth, axis=1)
    radii = confidence_radii(solution.covariances)
    assert np.all(errors <= radii)
    assert "mirror image" in solution.fit.detail
    # Some land on the wrong side, which only the widening covers (each twin is exact).
    mirrored = np.abs((2.0 * 1.0 - solution.positions[:, 1]) - truth[:, 1]) < 0.05
    assert np.any(mirrored & (errors > 0.3))


def test_the_paper_room_has_no_twins(paper_fingerprint: Fingerprint) -> None:
    solver = GridlessSolver(paper_fingerprint, "correlation")
    layout = paper_fingerprint.layout
    truth = random_positions(layout, 6, rng=np.random.default_rng(5))
    simulated = simulate_terminals(layout, truth, Impairments.ideal(), snr_db=30.0, rng=5)
    solution = solver.solve_terminals(simulated.amplitudes)
    assert solution.fit is not None and "mirror" not in solution.fit.detail


def test_rooms_without_twins_anywhere_skip_the_check(paper_fingerprint: Fingerprint) -> None:
    """The check is skipped only where no grid point has a twin even under looser limits."""
    paper = paper_fingerprint.layout
    assert not twins_possible(paper.cell_centres(), led_xy(paper), gains_of(paper), (4.0, 4.0))
    assert not GridlessSolver(paper_fingerprint, "correlation").room.twins_possible
    row = corridor()
    assert twins_possible(row.cell_centres(), led_xy(row), gains_of(row), (6.0, 2.5))
    assert GridlessSolver(build_fingerprint(row), "correlation").room.twins_possible


def test_far_optima_finds_the_other_side_of_a_row() -> None:
    """A terminal's own amplitudes, gain free: on one side of a row of LEDs, the grid points
    on the other side explain them as well (a far optimum); in the paper room's array, the
    region stays around the estimate."""
    layout = corridor()
    points = layout.cell_centres()
    gains = channel_gains(layout, points)
    truth = np.array([[2.2, 0.4]])
    amplitudes = channel_gains(layout, truth).T * 0.8  # any gain
    tight = np.eye(2)[np.newaxis] * 1e-4
    noise = 1e-3 * float(amplitudes.max())
    far = far_optima(amplitudes, gains, points, truth, tight, noise**2, 0.1)
    assert np.linalg.norm(far[0] - [2.2, 1.6]) < 0.15  # the mirror image across y = 1
    # With a covariance whose circle already reaches there (1.47 m), nothing is far.
    wide = np.eye(2)[np.newaxis] * 0.6**2
    assert np.isnan(far_optima(amplitudes, gains, points, truth, wide, noise**2, 0.1)).all()


def _corridor_terminal(x: float, y: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The corridor's grid points (N, 2), their gains (M, N), a terminal at ``(x, y)`` (1, 2)
    and its noiseless amplitudes (1, M)."""
    layout = corridor()
    points = layout.cell_centres()
    truth = np.array([[x, y]])
    return points, channel_gains(layout, points), truth, channel_gains(layout, truth).T


def test_far_optima_weigh_the_gain_by_its_prior() -> None:
    """With a prior on the gain the profile is the cost minimised over the gain with that
    prior (here by a scalar search per grid point); the row's mirror image, explained by
    the same gain, is still far."""
    points, gains, truth, clean = _corridor_terminal(2.2, 0.4)
    noise = 1e-3 * float(clean.max())
    amplitudes = clean * 1.05 + noise * np.random.default_rng(3).standard_normal(clean.shape)
    tight = np.eye(2)[np.newaxis] * 1e-4
    gain_sd = 0.1
    lam = noise**2 / gain_sd**2

    def cost(a: float, j: int) -> float:
        return float(np.sum((amplitudes[0] - a * gains[:, j]) ** 2) + lam * (a - 1.0) ** 2)

    profile = np.array(
        [[optimize.minimize_scalar(cost, args=(j,)).fun for j in range(points.shape[0])]]
    )
    explained = -profile / noise**2
    expected = farthest_in_region(explained, explained.max(axis=1), points, truth, tight, 0.1)
    far = far_optima(amplitudes, gains, points, truth, tight, noise**2, 0.1, gain_sd=gain_sd)
    np.testing.assert_array_equal(far, expected)
    assert np.linalg.norm(far[0] - [2.2, 1.6]) < 0.15


def test_a_far_place_that_needs_another_gain_is_not_far_under_its_prior() -> None:
    """A terminal beyond the end of a corridor's row of LEDs: with its gain free, places
    across the corridor explain its amplitudes scaled; under a 10 % prior on the gain
    the region reaches less far."""
    points, gains, truth, clean = _corridor_terminal(0.3, 1.0)
    noise = 1e-2 * float(clean.max())
    tight = np.eye(2)[np.newaxis] * 1e-4
    free = far_optima(clean, gains, points, truth, tight, noise**2, 0.1)
    held = far_optima(clean, gains, points, truth, tight, noise**2, 0.1, gain_sd=0.1)
    free_reach = float(np.linalg.norm(free[0] - truth[0]))
    held_reach = float(np.linalg.norm(held[0] - truth[0])) if np.isfinite(held).all() else 0.0
    assert free_reach > 0.9 and held_reach < 0.7


def test_far_optima_leave_a_well_lit_terminal_alone(paper_fingerprint: Fingerprint) -> None:
    layout = paper_fingerprint.layout
    points = layout.cell_centres()
    gains = channel_gains(layout, points)
    truth = random_positions(layout, 20, rng=np.random.default_rng(2))
    amplitudes = channel_gains(layout, truth).T
    noise = 1e-3 * float(amplitudes.max())  # 30 dB
    covariances = np.repeat(np.eye(2)[np.newaxis] * 0.02**2, 20, axis=0)
    far = far_optima(amplitudes, gains, points, truth, covariances, noise**2, 0.2)
    assert np.isnan(far).all()


def test_the_farthest_point_of_a_profile_region_beyond_the_circle() -> None:
    points = np.array([[0.0, 0.0], [0.1, 0.0], [2.0, 0.0], [3.0, 0.0]])
    positions = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    tight = np.repeat(np.eye(2)[np.newaxis] * 1e-4, 3, axis=0)
    explained = np.array(
        [
            [10.0, 9.0, 5.0, 0.0],  # (2, 0) is within 5.99 of the best, (3, 0) is not
            [10.0, 9.0, 3.0, 0.0],  # only the neighbourhood
            [10.0, 9.0, 5.0, 0.0],  # the same, but the estimate itself explains 20
        ]
    )
    far = farthest_in_region(explained, np.array([10.0, 10.0, 20.0]), points, positions, tight, 0.1)
    assert np.array_equal(far[0], [2.0, 0.0])
    assert np.isnan(far[1:]).all()
    # A circle that already reaches past (2, 0) (radius 2.45 sqrt(0.81) = 2.2 m): not far.
    wide = np.eye(2)[np.newaxis] * 0.81
    assert np.isnan(
        farthest_in_region(explained[:1], np.array([10.0]), points, positions[:1], wide, 0.1)
    ).all()


def test_the_estimates_whose_profile_region_reaches_beyond_a_distance() -> None:
    points = np.array([[0.0, 0.0], [0.1, 0.0], [2.0, 0.0], [3.0, 0.0]])
    positions = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [3.0, 0.0]])
    explained = np.array(
        [
            [10.0, 9.0, 5.0, 0.0],  # (2, 0), 2 m away, is within 5.99 of the best
            [10.0, 9.0, 3.0, 0.0],  # only the neighbourhood
            [10.0, 9.0, 5.0, 0.0],  # the same, but the estimate itself explains 20
            [10.0, 9.0, 5.0, 0.0],  # at (3, 0): (0, 0) is 3 m away, (2, 0) 1 m
        ]
    )
    best = np.array([10.0, 10.0, 20.0, 10.0])
    # Each estimate's region, brute force: the points within chi-square(2)'s 95 % quantile
    # of its best.
    quantile = stats.chi2.ppf(0.95, 2)
    for distance in (0.05, 0.5, 1.5, 2.5):
        want = [
            k
            for k in range(4)
            if any(
                explained[k, j] >= best[k] - quantile
                and np.hypot(*(points[j] - positions[k])) > distance
                for j in range(4)
            )
        ]
        got = reaching_beyond(explained, best, points, positions, distance)
        assert got.tolist() == want
    assert reaching_beyond(explained, best, points, positions, 1.5).tolist() == [0, 3]
    assert reaching_beyond(explained, best, points, positions, 2.5).tolist() == [3]


def test_terminals_in_the_dark_get_radii_that_hold_them() -> None:
    """Narrow beams far apart: a terminal between them receives noise only, and any dark
    spot explains that as well. Before, such answers came with radii of a metre or two at
    the wrong end of the room (random rooms, 2026-11-24)."""
    layout = Layout(
        room=Room(6.0, 5.0, 3.5),
        grid=Grid(0.25, 0.5),
        leds=tuple(
            Led(x=x, y=y, z=3.5, half_power_angle_deg=15.0)
            for x in (1.5, 4.5)
            for y in (1.25, 3.75)
        ),
    )
    solver = GridlessSolver(build_fingerprint(layout), "correlation")
    rng = np.random.default_rng(4)
    dark = np.array([[3.0, 2.5], [0.3, 2.5], [5.7, 0.2], [3.0, 4.8], [0.2, 4.8]])
    simulated = simulate_terminals(layout, dark, Impairments.ideal(), snr_db=30.0, rng=rng)
    solution = solver.solve_terminals(simulated.amplitudes)
    assert solution.covariances is not None and solution.fit is not None
    errors = np.linalg.norm(solution.positions - dark, axis=1)
    assert np.all(errors <= confidence_radii(solution.covariances))
    assert "another place" in solution.fit.detail
