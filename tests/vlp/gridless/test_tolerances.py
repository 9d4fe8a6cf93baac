"""The aggregated fit with the room's tolerances (LED amplitudes and beams, tilts) as nuisances."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout, Reflectance
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.metrics import mean_position_error
from app.vlp.radii import confidence_radii
from app.vlp.simulation import Impairments, random_positions, simulate_terminals
from app.vlp.solvers.gridless.fitting import Run
from app.vlp.solvers.gridless.joint_model import (
    JointModel,
    RoomTolerances,
)
from app.vlp.solvers.gridless.search import refine
from app.vlp.solvers.gridless.solver import GridlessOptions, GridlessSolver
from app.vlp.solvers.gridless.stages import tolerance_tilt_sd, with_room_tolerances
from app.vlp.solvers.gridless.state import FitState
from app.vlp.solvers.gridless.tolerances import (
    GridMoves,
    fit_room_tolerances,
)
from app.vlp.solvers.gridless.whitening import (
    Whitening,
    target_gains,
    whitening_reference,
)

_TOLERANCES = RoomTolerances(led_log_amplitude_sd=0.05, led_half_power_sd_deg=3.0, tilt_sd=0.07)


@pytest.fixture(scope="module")
def reflecting_solver(paper_room: Layout) -> GridlessSolver:
    room = dataclasses.replace(
        paper_room.room, reflectance=Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
    )
    layout = dataclasses.replace(paper_room, room=room)
    return GridlessSolver(build_fingerprint(layout), "correlation")


def _state(rng: np.random.Generator, k: int, height: float) -> FitState:
    return FitState(
        rng.uniform(0.5, 3.5, (k, 2)),
        np.ones(k),
        0.01,
        np.full(k, height),
        0.05 * rng.standard_normal(k),
        0.1,
    )


@pytest.mark.parametrize("tilt_sd", [0.07, 0.0])
def test_jacobian_matches_central_differences(
    reflecting_solver: GridlessSolver, tilt_sd: float
) -> None:
    rng = np.random.default_rng(0)
    k = 3
    kernel = reflecting_solver.room.kernel
    state = _state(rng, k, kernel.receiver_height)
    tolerances = dataclasses.replace(_TOLERANCES, tilt_sd=tilt_sd)
    model = JointModel(kernel, state.heights, (0.1, 0.5), tolerances)
    assert model.size() == 3 * k + 2 * 16 + (2 * k if tilt_sd else 0) + 2
    theta = model.pack(state)
    theta[3 * k + 1 : -1] = 0.05 * rng.standard_normal(theta.shape[0] - 3 * k - 2)
    white = model.whitening(theta, 0.01)
    data = white.data(rng.standard_normal(136))
    _, jacobian = model.residual_and_jacobian(theta, white, data)
    numeric = np.empty_like(jacobian)
    for i in range(theta.shape[0]):
        step = np.zeros_like(theta)
        step[i] = 1e-6 * max(1.0, abs(theta[i]))
        plus = model.residual_and_jacobian(theta + step, white, data)[0]
        minus = model.residual_and_jacobian(theta - step, white, data)[0]
        # J is the derivative of the model, the residual's is -J.
        numeric[:, i] = -(plus - minus) / (2.0 * step[i])
    np.testing.assert_allclose(jacobian, numeric, rtol=1e-5, atol=1e-6 * np.abs(jacobian).max())


def test_without_tolerances_the_model_is_the_solver_s(reflecting_solver: GridlessSolver) -> None:
    rng = np.random.default_rng(1)
    kernel = reflecting_solver.room.kernel
    state = _state(rng, 4, kernel.receiver_height)
    model = JointModel(kernel, state.heights, (0.1, 0.5), _TOLERANCES)
    theta = model.pack(state)
    gains, multipliers, _ = model.gains(theta)
    np.testing.assert_allclose(gains, target_gains(kernel, state), rtol=1e-12)
    np.testing.assert_allclose(multipliers, state.effective_weights(), rtol=1e-12)
    # Its metric is the solver's plug-in whitening. The eigenbasis of the noise-only
    # subspace is arbitrary, so compare what is not: the weights and the matrix that the
    # rotation and the diagonal entries' weights (1 / (8 sigma^2 lam)) describe.
    ours = model.whitening(theta, state.noise)
    reference = whitening_reference("correlation", kernel, state, 4.0)
    np.testing.assert_allclose(ours.weights, reference.weights, rtol=1e-10)

    def spectrum_matrix(white: Whitening) -> np.ndarray:
        assert white.rotation is not None
        lam = 1.0 / white.weights[white.is_diag == 1.0] ** 2
        return np.asarray((white.rotation * lam) @ white.rotation.T)

    np.testing.assert_allclose(spectrum_matrix(ours), spectrum_matrix(reference), rtol=1e-9)


def _errors(
    fingerprint: Fingerprint, impairments: Impairments, with_stage: bool, seeds: range, k: int
) -> list[float]:
    options = GridlessOptions() if with_stage else GridlessOptions(led_log_amplitude_sd=None)
    solver = GridlessSolver(fingerprint, "correlation", options)
    layout = fingerprint.layout
    errors = []
    for seed in seeds:
        truth = random_positions(layout, k, rng=np.random.default_rng(1000 + seed))
        simulated = simulate_terminals(layout, truth, impairments, snr_db=30.0, rng=seed)
        measurement = measurement_from_amplitudes(simulated.amplitudes, "correlation", 16)
        errors.append(mean_position_error(solver.solve(measurement, k).positions, truth))
    return errors


def test_led_tolerances_are_fitted_out(paper_fingerprint: Fingerprint) -> None:
    # LEDs 5 % / 3 degrees off their data sheet: the aggregated fit without the stage is
    # biased by 15-20 cm at K = 8 (docs/decisions/room-tolerance-stage.md), with it about half.
    impairments = Impairments.led_tolerances(0.05, 3.0)
    without = _errors(paper_fingerprint, impairments, False, range(6), 8)
    with_stage = _errors(paper_fingerprint, impairments, True, range(6), 8)
    assert np.mean(with_stage) < 0.75 * np.mean(without)
    assert np.median(with_stage) < 0.15


def _led_tolerance_details(solver: GridlessSolver) -> list[str]:
    """``fit.detail`` of four K = 8 answers under LED tolerances (5 %, 3 degrees)."""
    layout = solver.fingerprint.layout
    details = []
    for seed in range(4):
        truth = random_positions(layout, 8, rng=np.random.default_rng(1000 + seed))
        simulated = simulate_terminals(
            layout, truth, Impairments.led_tolerances(0.05, 3.0), snr_db=30.0, rng=seed
        )
        measurement = measurement_from_amplitudes(simulated.amplitudes, "correlation", 16)
        solution = solver.solve(measurement, 8)
        assert solution.fit is not None
        details.append(solution.fit.detail)
    return details


def test_an_answer_says_when_the_tolerances_were_fitted(paper_fingerprint: Fingerprint) -> None:
    details = _led_tolerance_details(GridlessSolver(paper_fingerprint, "correlation"))
    said = [detail for detail in details if "tolerances were fitted" in detail]
    assert len(said) >= 2
    # The fitted spread is of the drawn tolerances' size (5 %, 3 degrees), not wild.
    for detail in said:
        amplitude = float(detail.split("amplitudes ")[1].split(" %")[0])
        angle = float(detail.split("half-power angles ")[1].split(" deg")[0])
        assert 1.0 < amplitude < 12.0
        assert 0.5 < angle < 8.0


def test_the_score_test_s_bar_gates_the_stage(paper_fingerprint: Fingerprint) -> None:
    """``tolerance_score_ratio``: the first Gauss-Newton step must promise more than that
    many times the extra parameters; an unreachable bar keeps every fit nominal, where the
    default fits the LEDs' tolerances of most of these rooms."""
    fitted = {}
    for ratio in (1.0, math.inf):
        options = GridlessOptions(tolerance_score_ratio=ratio)
        details = _led_tolerance_details(GridlessSolver(paper_fingerprint, "correlation", options))
        fitted[ratio] = sum("tolerances were fitted" in detail for detail in details)
    assert fitted[1.0] >= 2
    assert fitted[math.inf] == 0


def test_radii_of_the_joint_fit_hold_the_truth(paper_fingerprint: Fingerprint) -> None:
    # The joint fit's covariance carries the tolerances' uncertainty: its 95 % circles
    # hold the truth about as often as they say, and are not absurdly wide.
    solver = GridlessSolver(paper_fingerprint, "correlation")
    layout = paper_fingerprint.layout
    inside, radii, errors = [], [], []
    for seed in range(6):
        truth = random_positions(layout, 8, rng=np.random.default_rng(1000 + seed))
        simulated = simulate_terminals(
            layout, truth, Impairments.led_tolerances(0.05, 3.0), snr_db=30.0, rng=seed
        )
        solution = solver.solve(
            measurement_from_amplitudes(simulated.amplitudes, "correlation", 16), 8
        )
        assert solution.covariances is not None
        radius = confidence_radii(solution.covariances)
        rows, cols = linear_sum_assignment(
            np.linalg.norm(truth[:, None, :] - solution.positions[None, :, :], axis=2)
        )
        error = np.linalg.norm(truth[rows] - solution.positions[cols], axis=1)
        inside += list(error <= radius[cols])
        radii += list(radius[cols])
        errors += list(error)
    assert np.mean(inside) >= 0.8
    assert np.median(radii) <= 6.0 * np.median(errors)


def test_an_ideal_room_keeps_the_fit_without_tolerances(paper_fingerprint: Fingerprint) -> None:
    # The stage must not cost the ideal model its accuracy: its significance test keeps it
    # out of nearly every fit of a room exactly as modelled (it let in 2-3 of 120 K = 8
    # fits; 24 seeds so that one or two chance entries do not decide the test).
    without = _errors(paper_fingerprint, Impairments.ideal(), False, range(24), 8)
    with_stage = _errors(paper_fingerprint, Impairments.ideal(), True, range(24), 8)
    same = sum(a == b for a, b in zip(without, with_stage, strict=True))
    assert same >= 21
    assert np.mean(with_stage) <= np.mean(without) + 0.005


# Placements tried for a refinement that stays stuck (each a fraction of a second).
STUCK_SEEDS = 20


def _stuck_fit(
    fingerprint: Fingerprint, seed: int, jumps: bool
) -> tuple[GridlessSolver, Run, FitState, np.ndarray]:
    """Six terminals under LED tolerances, and the nominal fit refined (no escapes) from a
    start that puts the first estimate next to the terminal farthest from the first's."""
    layout = fingerprint.layout
    truth = random_positions(layout, 6, rng=np.random.default_rng(50 + seed))
    simulated = simulate_terminals(
        layout, truth, Impairments.led_tolerances(0.05, 3.0), snr_db=30.0, rng=seed
    )
    measurement = measurement_from_amplitudes(simulated.amplitudes, "correlation", 16)
    solver = GridlessSolver(fingerprint, "correlation", GridlessOptions(tolerance_jumps=jumps))
    run = Run(values=measurement.values / solver.room.scale**2, priors=solver.room.growth_priors)
    farthest = int(np.argmax(np.linalg.norm(truth - truth[0], axis=1)))
    start = truth.copy()
    start[0] = truth[farthest] + np.array([0.15 if truth[farthest, 0] < 3.5 else -0.15, 0.0])
    heights = np.full(6, layout.grid.receiver_height)
    state = FitState(start, np.ones(6), 0.0, heights, np.zeros(6), 0.0)
    return solver, run, refine(solver.room, run, state, 50, 3), truth


def _matched_errors(estimates: np.ndarray, truth: np.ndarray) -> np.ndarray:
    distances = np.linalg.norm(estimates[:, None, :] - truth[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(distances)
    return np.asarray(distances[rows, cols])


def test_a_target_on_another_s_terminal_jumps_to_the_one_left_without(
    paper_fingerprint: Fingerprint,
) -> None:
    # Two estimates on one terminal and none on another is a local optimum that the joint
    # fit's own refinement does not leave; its long moves mostly do. Not always: a move is
    # kept when it lowers the cost, and one stuck seed's moves can all fail (5-8 of 20 seeds
    # stay stuck, 1-2 of them unfixed, depending on the machine's round-off). So the stuck
    # seeds are held together: at least two and half of them fixed, their mean worst error
    # at least halved. Where the refinement alone already finds every terminal, the moves
    # change nothing for the worse: a kept move can shift an estimate by a noise-sized step
    # either way (up to 2.1 cm on one machine), so a single placement is held to the noise
    # (5 cm, about the bound at K = 8) and the mean change to 1 cm.
    stuck: list[tuple[float, float]] = []
    changes = []
    for seed in range(STUCK_SEEDS):
        worst = {}
        for jumps in (False, True):
            solver, run, state, truth = _stuck_fit(paper_fingerprint, seed, jumps)
            fitted = with_room_tolerances(solver.room, run, state)
            assert fitted is not None  # the wrong optimum shows a misfit
            worst[jumps] = float(_matched_errors(fitted.state.positions, truth).max())
        if worst[False] > 1.0:
            stuck.append((worst[False], worst[True]))
        else:
            assert worst[True] <= worst[False] + 0.05
            changes.append(worst[True] - worst[False])
    without, moved = np.array(stuck).T
    fixed = int(np.sum(moved < 0.25))
    assert fixed >= 2 and fixed >= len(stuck) / 2
    assert np.mean(moved) <= 0.5 * np.mean(without)
    assert np.mean(changes) <= 0.01


def test_the_joint_fit_takes_another_placement_only_when_it_fits_better(
    paper_fingerprint: Fingerprint,
) -> None:
    def fit(start: FitState, alternatives: tuple[np.ndarray, ...]) -> np.ndarray:
        # No long moves of single targets (nothing is that far): only the placements.
        kernel, opts = solver.room.kernel, solver.options
        tolerances = RoomTolerances(
            opts.led_log_amplitude_sd or 0.0, opts.led_half_power_sd_deg, 0.0
        )
        priors = (opts.log_gain_sd or 0.0, opts.log_scale_sd or 0.0)
        height = solver.room.priors.height_mean
        moves = GridMoves(solver.room.gains, solver.room.centres, np.inf, height, alternatives)
        fitted = fit_room_tolerances(kernel, run.values, start, priors, tolerances, 3.0, moves)
        assert fitted is not None
        return fitted.state.positions

    # The first seed whose joint fit stays stuck (round-off decides which: see above).
    stuck = False
    for seed in range(STUCK_SEEDS):
        solver, run, state, truth = _stuck_fit(paper_fingerprint, seed, jumps=False)
        wrong = fit(state, ())
        stuck = bool(_matched_errors(wrong, truth).max() > 1.0)
        if stuck:
            break
    assert stuck
    right = fit(state, (truth,))
    assert _matched_errors(right, truth).max() < 0.25
    # From the right optimum, the wrong placement is tried and left.
    good_start = refine(solver.room, run, dataclasses.replace(state, positions=truth.copy()), 50, 3)
    from_good = fit(good_start, ())
    np.testing.assert_array_equal(fit(good_start, (state.positions,)), from_good)


def _merged_pair_fit(
    fingerprint: Fingerprint, seed: int
) -> tuple[GridlessSolver, Run, FitState, np.ndarray]:
    """Six terminals under LED tolerances, two of them 25 cm apart, and the nominal fit
    refined (no escapes) from a start with one estimate between the two and another next to
    a third terminal: the pair fitted as one bright estimate, a spare one elsewhere."""
    layout = fingerprint.layout
    rng = np.random.default_rng(70 + seed)
    truth = random_positions(layout, 6, rng=rng)
    truth[1] = np.clip(truth[0] + np.array([0.25, 0.0]), 0.1, layout.room.length - 0.1)
    truth[0] = truth[1] - np.array([0.25, 0.0])
    simulated = simulate_terminals(
        layout, truth, Impairments.led_tolerances(0.05, 3.0), snr_db=30.0, rng=seed
    )
    measurement = measurement_from_amplitudes(simulated.amplitudes, "correlation", 16)
    solver = GridlessSolver(fingerprint, "correlation")
    run = Run(values=measurement.values / solver.room.scale**2, priors=solver.room.growth_priors)
    start = truth.copy()
    start[0] = 0.5 * (truth[0] + truth[1])
    start[1] = truth[2] + np.array([0.15 if truth[2, 0] < 3.5 else -0.15, 0.0])
    heights = np.full(6, layout.grid.receiver_height)
    state = FitState(start, np.ones(6), 0.0, heights, np.zeros(6), 0.0)
    return solver, run, refine(solver.room, run, state, 50, 3), truth


def test_a_close_pair_fitted_as_one_bright_estimate_is_split(
    paper_fingerprint: Fingerprint,
) -> None:
    """The joint fit tries the brightest estimate as two, the estimate that explains least
    moved beside it (``GridMoves.split_offset``), and keeps that when it lowers the cost.
    No long moves here: from this start the joint fit's own refinement leaves some seeds
    merged."""
    worst: dict[float, list[float]] = {0.0: [], 0.1: []}
    for seed in range(12):  # 7 of them stay merged without the split on one machine
        solver, run, state, truth = _merged_pair_fit(paper_fingerprint, seed)
        opts = solver.options
        tolerances = RoomTolerances(
            opts.led_log_amplitude_sd or 0.0, opts.led_half_power_sd_deg, 0.0
        )
        priors = (opts.log_gain_sd or 0.0, opts.log_scale_sd or 0.0)
        for offset in worst:
            moves = GridMoves(
                solver.room.gains,
                solver.room.centres,
                np.inf,
                solver.room.priors.height_mean,
                (),
                offset,
            )
            fitted = fit_room_tolerances(
                solver.room.kernel, run.values, state, priors, tolerances, 3.0, moves
            )
            assert fitted is not None  # a merged pair shows a misfit
            worst[offset].append(float(_matched_errors(fitted.state.positions, truth).max()))
    merged, split = np.array(worst[0.0]), np.array(worst[0.1])
    # Where the joint fit stays merged (a spare estimate metres off), the split finds the
    # pair; held together, as the long moves' test does (a move is kept only when it lowers
    # the cost, which round-off can decide). Elsewhere it changes nothing for the worse.
    stuck = merged > 1.0
    assert stuck.sum() >= 2
    fixed = int(np.sum(split[stuck] < 0.25))
    assert fixed >= 2 and fixed >= stuck.sum() / 2
    assert np.all(split[~stuck] <= merged[~stuck] + 0.05)


def _tilted_errors(
    fingerprint: Fingerprint, options: GridlessOptions, seeds: range
) -> tuple[list[float], list[str]]:
    """Mean errors and fit details of K = 8 answers with hand-held photodiodes (tilted
    0-20 degrees) under LED tolerances (5 %, 3 degrees), 30 dB."""
    impairments = Impairments(tilt_max_deg=20.0, led_amplitude_sd=0.05, led_half_power_sd_deg=3.0)
    solver = GridlessSolver(fingerprint, "correlation", options)
    layout = fingerprint.layout
    errors, details = [], []
    for seed in seeds:
        truth = random_positions(layout, 8, rng=np.random.default_rng(2000 + seed))
        simulated = simulate_terminals(layout, truth, impairments, snr_db=30.0, rng=seed)
        measurement = measurement_from_amplitudes(simulated.amplitudes, "correlation", 16)
        solution = solver.solve(measurement, 8)
        assert solution.fit is not None
        errors.append(mean_position_error(solution.positions, truth))
        details.append(solution.fit.detail)
    return errors, details


def test_hand_held_photodiodes_tilts_are_fitted_after_the_tolerances(
    paper_fingerprint: Fingerprint,
) -> None:
    """Where the joint fit is kept, the photodiodes' tilts are fitted from its optimum
    (prior ``tolerance_tilt_sd``): on tilted terminals the answers land closer than the same fits
    with the tilts held level, most of them (docs/decisions/tilts-after-tolerances.md), and say
    so."""
    seeds = range(16)
    level, _ = _tilted_errors(paper_fingerprint, GridlessOptions(tolerance_tilt_sd=0.0), seeds)
    tilted, details = _tilted_errors(paper_fingerprint, GridlessOptions(), seeds)
    assert np.mean(tilted) < 0.95 * np.mean(level)
    assert sum(a < b for a, b in zip(tilted, level, strict=True)) >= 10
    assert any("the photodiodes' tilts" in detail for detail in details)


def test_a_level_room_fits_no_tilts(paper_room: Layout) -> None:
    """A layout whose photodiodes are level: the answers are those with the stage off."""
    grid = dataclasses.replace(paper_room.grid, receivers_level=True)
    fingerprint = build_fingerprint(dataclasses.replace(paper_room, grid=grid))
    seeds = range(3)
    off, _ = _tilted_errors(fingerprint, GridlessOptions(tolerance_tilt_sd=0.0), seeds)
    default, details = _tilted_errors(fingerprint, GridlessOptions(), seeds)
    assert default == off
    assert not any("the photodiodes' tilts" in detail for detail in details)
    assert any("tolerances were fitted" in detail for detail in details)


def test_the_tilts_prior_is_the_layout_s_spread_else_the_hand_held_default(
    paper_room: Layout, paper_fingerprint: Fingerprint
) -> None:
    def prior(fingerprint: Fingerprint, options: GridlessOptions) -> float:
        return tolerance_tilt_sd(GridlessSolver(fingerprint, "correlation", options).room)

    spread = dataclasses.replace(paper_room.grid, receiver_tilt_sd=4.0)
    declared = build_fingerprint(dataclasses.replace(paper_room, grid=spread))
    assert prior(declared, GridlessOptions()) == pytest.approx(math.radians(4.0))
    assert prior(paper_fingerprint, GridlessOptions()) == GridlessOptions().tolerance_tilt_sd
    assert prior(paper_fingerprint, GridlessOptions(tolerance_tilt_sd=0.2)) == 0.2
    assert prior(declared, GridlessOptions(tolerance_tilt_sd=0.0)) == 0.0
