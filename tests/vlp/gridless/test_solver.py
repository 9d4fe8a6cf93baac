"""The default gridless solver: exact noiseless recovery off the grid, accuracy, counting."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from app.vlp import fingerprints
from app.vlp.channel import channel_gain_gradients
from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.measurements import Measurement, Model, measurement_from_amplitudes
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers import make_solver, solver_names
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver
from app.vlp.solvers.gridless.channel import ChannelKernel

GRID_FLOOR_M = 0.0765  # mean quantisation error of the 0.2 m grid


def matched_error(truth: np.ndarray, estimate: np.ndarray) -> float:
    """Mean distance after the best one-to-one matching."""
    cost = np.linalg.norm(truth[:, None, :] - estimate[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def simulate(
    layout: Layout,
    fp: Fingerprint,
    truth: np.ndarray,
    snr_db: float | None,
    model: Model,
    rng: np.random.Generator,
) -> Measurement:
    sigma = 0.0 if snr_db is None else noise_std_for_snr(fp, snr_db)
    amps = noisy_amplitudes(layout, truth, sigma, rng=rng)
    return measurement_from_amplitudes(amps, model, layout.n_leds)


def test_registered_as_the_default(paper_fingerprint: Fingerprint) -> None:
    assert solver_names()[0] == "gridless"
    assert isinstance(make_solver("gridless", paper_fingerprint, "power"), GridlessSolver)


@pytest.mark.parametrize("n_targets", [1, 2, 3])
def test_noiseless_off_grid_positions_are_recovered_exactly(
    paper_room: Layout, paper_fingerprint: Fingerprint, paper_solver: GridlessSolver, n_targets: int
) -> None:
    truth = random_positions(paper_room, n_targets, rng=100 + n_targets)
    meas = simulate(
        paper_room, paper_fingerprint, truth, None, "correlation", np.random.default_rng(0)
    )
    sol = paper_solver.solve(meas, n_targets)
    assert matched_error(truth, sol.positions) < 1e-3
    np.testing.assert_allclose(sol.weights, 1.0)
    assert sol.noise_power == pytest.approx(0.0, abs=1e-6 * float(meas.values.max()))


def test_beats_the_grid_floor_between_grid_points(
    paper_room: Layout,
    paper_fingerprint: Fingerprint,
    paper_solver: GridlessSolver,
    rng: np.random.Generator,
) -> None:
    truth = random_positions(paper_room, 2, rng=rng)
    meas = simulate(paper_room, paper_fingerprint, truth, 30.0, "correlation", rng)
    sol = paper_solver.solve(meas, 2)
    assert matched_error(truth, sol.positions) < GRID_FLOOR_M
    # Refined positions are not snapped to grid centres; grid_indices are their cells.
    centres = paper_room.cell_centres(sol.grid_indices)
    assert np.all(np.linalg.norm(sol.positions - centres, axis=1) > 1e-6)
    np.testing.assert_array_equal(sol.grid_indices, paper_room.nearest_cell(sol.positions))
    assert sol.n_targets == 2 and sol.converged


def test_converged_reports_the_final_fit_not_the_last_candidate(
    paper_room: Layout, paper_fingerprint: Fingerprint, paper_solver: GridlessSolver
) -> None:
    """The growth steps' short fits run out of iterations by design; the answer's
    ``converged`` is the final refinement's: true with the default budget, false when the
    final refinement is starved of iterations (one per round, one round)."""
    starved = GridlessSolver(
        paper_fingerprint, "correlation", GridlessOptions(final_iter=1, whiten_rounds=1)
    )
    for seed in range(4):
        rng = np.random.default_rng(seed)
        truth = random_positions(paper_room, 3, rng=rng)
        meas = simulate(paper_room, paper_fingerprint, truth, 30.0, "correlation", rng)
        assert paper_solver.solve(meas, 3).converged
        assert not starved.solve(meas, 3).converged


def test_mean_error_over_seeds_stays_below_the_grid_floor(
    paper_room: Layout, paper_fingerprint: Fingerprint, paper_solver: GridlessSolver
) -> None:
    errors = []
    for seed in range(10):
        gen = np.random.default_rng(seed)
        truth = random_positions(paper_room, 4, rng=gen)
        meas = simulate(paper_room, paper_fingerprint, truth, 30.0, "correlation", gen)
        errors.append(matched_error(truth, paper_solver.solve(meas, 4).positions))
    assert float(np.mean(errors)) < GRID_FLOOR_M


@pytest.mark.parametrize("n_targets", [1, 2])
def test_power_model(paper_room: Layout, paper_fingerprint: Fingerprint, n_targets: int) -> None:
    solver = GridlessSolver(paper_fingerprint, "power")
    truth = random_positions(paper_room, n_targets, rng=7 + n_targets)
    exact = solver.solve(
        simulate(paper_room, paper_fingerprint, truth, None, "power", np.random.default_rng(1)),
        n_targets,
    )
    assert matched_error(truth, exact.positions) < 1e-3
    gen = np.random.default_rng(11)
    noisy = solver.solve(
        simulate(paper_room, paper_fingerprint, truth, 40.0, "power", gen), n_targets
    )
    assert matched_error(truth, noisy.positions) < GRID_FLOOR_M


@pytest.mark.parametrize("dense", [True, False], ids=["dense", "sparse"])
def test_other_room_both_code_paths(
    mixed_room: Layout, dense: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not dense:
        monkeypatch.setattr(fingerprints, "DENSE_GAINS_LIMIT", 0)
    fp = build_fingerprint(mixed_room)
    assert fp.is_dense is dense
    solver = GridlessSolver(fp, "correlation")
    # Each seen by 3 LEDs, at least 2 deg inside the 40 deg FOV of each (at the FOV edge
    # the gain jumps, and a target sitting on it is not well posed).
    truth = np.array([[1.0, 1.4], [2.2, 1.5]])
    meas = simulate(mixed_room, fp, truth, None, "correlation", np.random.default_rng(3))
    sol = solver.solve(meas, 2)
    assert matched_error(truth, sol.positions) < 1e-3
    assert np.all((sol.positions >= 0) & (sol.positions <= [3.0, 2.0]))


def test_one_solver_object_serves_threads(
    paper_room: Layout, paper_fingerprint: Fingerprint, paper_solver: GridlessSolver
) -> None:
    # Solver objects are cached and shared by the web layer: no per-call state on self.
    measurements = [
        simulate(
            paper_room,
            paper_fingerprint,
            random_positions(paper_room, 3, rng=seed),
            30.0,
            "correlation",
            np.random.default_rng(seed),
        )
        for seed in range(4)
    ]
    sequential = [paper_solver.solve(m, 3) for m in measurements]
    with ThreadPoolExecutor(max_workers=4) as pool:
        parallel = list(pool.map(lambda m: paper_solver.solve(m, 3), measurements))
    for one, other in zip(sequential, parallel, strict=True):
        np.testing.assert_array_equal(one.positions, other.positions)
        assert one.n_iter == other.n_iter


@pytest.mark.parametrize("room", ["paper", "mixed"])
def test_fast_kernel_matches_the_channel_model(
    paper_room: Layout, mixed_room: Layout, room: str
) -> None:
    layout = paper_room if room == "paper" else mixed_room
    kernel = ChannelKernel(layout, scale=2e-5)
    points = random_positions(layout, 6, rng=5)
    gains, grads = channel_gain_gradients(layout, points)
    pilots = layout.pilot_amplitudes[:, None]
    expected = np.concatenate([gains, grads[:, :, 0], grads[:, :, 1]], axis=1) * pilots / 2e-5
    np.testing.assert_allclose(
        kernel.stacked(points, with_gradients=True), expected, rtol=1e-10, atol=1e-12
    )
    np.testing.assert_allclose(
        kernel.stacked(points, with_gradients=False), expected[:, :6], rtol=1e-10, atol=1e-12
    )


@pytest.mark.slow
def test_large_sparse_hall(rng: np.random.Generator) -> None:
    # 30 m x 30 m, 0.1 m grid (90 000 points), 64 LEDs: above the dense limit, so only the
    # sparse H and the matrix-free Psi adjoint are used.
    spacing = 30.0 / 8
    leds = tuple(
        Led(spacing * (i + 0.5), spacing * (j + 0.5), 3.0) for i in range(8) for j in range(8)
    )
    hall = Layout(Room(30.0, 30.0, 3.0), Grid(0.1, 0.85), leds, Receiver(1e-4, 70.0, 1.0, 1.5))
    fp = build_fingerprint(hall)
    assert not fp.is_dense
    solver = GridlessSolver(fp, "correlation")
    truth = np.array([[4.03, 5.51], [20.77, 11.32], [12.18, 26.64]])
    meas = simulate(hall, fp, truth, 30.0, "correlation", rng)
    assert matched_error(truth, solver.solve(meas, 3).positions) < 0.05
    counted = solver.solve(meas)
    assert counted.n_targets == 3
    assert matched_error(truth, counted.positions) < 0.05
