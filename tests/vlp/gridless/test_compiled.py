"""The compiled kernels of the gridless solver against their NumPy references.

Each compiled kernel (``app/vlp/solvers/gridless/_compiled/channel.py``,
``gridless/_compiled/fit.py``, ``gridless/_compiled/tolerance.py``) must
give the numbers of the plain NumPy code it stands in for, to 1e-10 relative (normwise: a
difference is measured against the largest magnitude of the reference array), on random
inputs of several shapes, including one target (K = 1), one LED (M = 1) and one point.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import itertools
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize

from app.vlp._kernels import (
    dispatch,
    kernel_cache_dir,
    kernel_mode,
    use_kernels,
)
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Reflectance, Room
from app.vlp.measurements import Model, measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import true_amplitudes
from app.vlp.solvers import warm_up
from app.vlp.solvers._kernel_examples import random_state, unwhitened
from app.vlp.solvers._kernel_rooms import (
    LAYOUTS,
    TABLES,
    make_kernel,
    synthetic_table,
)
from app.vlp.solvers.gridless._compiled.channel import (
    channel_constants,
    channel_fields,
    channel_rows_kernel,
    diffuse_rows,
    whole_power,
)
from app.vlp.solvers.gridless._compiled.fit import (
    FitModel,
    _sparse_symmetric_product,
    fit_evaluate,
    fit_normal_equations,
    gram_kernel,
)
from app.vlp.solvers.gridless._compiled.uncertainty import (
    fit_misfit_kernel,
    misfit_design_kernel,
    nnls_kernel,
)
from app.vlp.solvers.gridless.channel import ChannelKernel
from app.vlp.solvers.gridless.fitting import Run
from app.vlp.solvers.gridless.joint_model import (
    JointModel,
    RoomTolerances,
)
from app.vlp.solvers.gridless.model import (
    Objective,
    fit_objective,
    gram,
    gram_reference,
)
from app.vlp.solvers.gridless.report import profiles
from app.vlp.solvers.gridless.search import grow, grow_kernel, refine, search_compiles
from app.vlp.solvers.gridless.solver import GridlessOptions, GridlessSolver
from app.vlp.solvers.gridless.state import (
    FitState,
    Priors,
)
from app.vlp.solvers.gridless.tolerances import _fit_joint
from app.vlp.solvers.gridless.uncertainty import sandwich_covariances, shape_gradients
from app.vlp.solvers.gridless.whitening import Whitening, whitening_reference
from app.vlp.typing import FloatArray
from app.vlp.uncertainty import MisfitDesign, fit_misfit, misfit_design_reference

RTOL = 1e-10
# The whole uncertainty chain (test_uncertainty_matches_reference): round-off amplified.
CHAIN_RTOL = 1e-8
REPO = Path(__file__).resolve().parents[3]


def assert_same(compiled: object, reference: object, rtol: float = RTOL) -> None:
    """Equal to ``rtol`` (1e-10) relative to the reference's largest magnitude."""
    got = np.asarray(compiled, dtype=np.float64)
    want = np.asarray(reference, dtype=np.float64)
    assert got.shape == want.shape
    scale = max(float(np.max(np.abs(want))), 1e-300) if want.size else 1.0
    np.testing.assert_allclose(got, want, rtol=0.0, atol=rtol * scale)


def normal(rng: np.random.Generator, size: int) -> FloatArray:
    """``size`` standard normal numbers."""
    return np.asarray(rng.standard_normal(size), dtype=np.float64)


def random_points(kernel: ChannelKernel, n_points: int, rng: np.random.Generator) -> FloatArray:
    length, width = kernel.bounds
    # Some points beyond the walls: the table clamps, the line of sight does not.
    return np.column_stack(
        (rng.uniform(-0.2, length + 0.2, n_points), rng.uniform(-0.2, width + 0.2, n_points))
    )


@pytest.mark.parametrize("exponent", [-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0])
def test_whole_powers_are_math_pow_within_round_off(exponent: float) -> None:
    bases = np.random.default_rng(11).uniform(1e-3, 40.0, 2000)
    got = np.array([whole_power(float(b), exponent) for b in bases])
    np.testing.assert_allclose(got, bases**exponent, rtol=1e-15, atol=0.0)


@pytest.mark.parametrize("exponent", [-2.5, -1.5, 0.5, 5.0, -6.0, 2.25])
def test_other_powers_are_math_pow(exponent: float) -> None:
    bases = np.random.default_rng(12).uniform(1e-3, 40.0, 500)
    got = np.array([whole_power(float(b), exponent) for b in bases])
    assert np.array_equal(got, [math.pow(float(b), exponent) for b in bases])


@pytest.mark.parametrize("layout_name", sorted(LAYOUTS))
def test_channel_fields_are_the_kernels_columns(layout_name: str) -> None:
    """The compiled channel's few stacked arrays give back each of the channel's columns,
    as the NumPy kernel holds them (the tilted and beamed LEDs' flags and tables too)."""
    kernel = make_kernel(layout_name, "flat", seed=2)
    constants = channel_constants(kernel)
    assert constants is not None
    fields = channel_fields(constants[0])
    beams = kernel.beams
    tilted = [bool(n[2] != -1.0 or n[0] != 0.0 or n[1] != 0.0) for n in kernel.normals]
    want = (
        kernel.led_xy[:, 0],
        kernel.led_xy[:, 1],
        kernel.led_z,
        kernel.dz2,
        kernel.factor,
        kernel.free_height_factor,
        kernel.orders,
        kernel.half_exponent,
        kernel.max_d2,
        kernel.pilot_over_scale,
        kernel.cos_fov2,
        kernel.receiver_height,
        kernel.normals,
        tilted,
        beams.beamed,
        beams.knots,
        beams.values,
        beams.slopes,
        beams.counts,
    )
    assert len(fields) == len(want)
    for got, column in zip(fields, want, strict=True):
        assert np.array_equal(np.asarray(got), np.asarray(column))
    if layout_name == "tilted":
        assert any(tilted)
    if layout_name == "beamed":
        assert np.asarray(fields[14]).any()


@pytest.mark.parametrize("heights", [False, True])
def test_diffuse_interpolation_matches_reference(heights: bool) -> None:
    layout = paper_layout()
    table = synthetic_table(layout, heights, seed=3)
    kernel = ChannelKernel(layout, 1.0, table)
    _, constants = channel_constants(kernel)  # type: ignore[misc]
    rng = np.random.default_rng(4)
    points = random_points(kernel, 9, rng)
    xs, ys = points[:, 0].copy(), points[:, 1].copy()
    zs = layout.grid.receiver_height + rng.uniform(-0.5, 0.5, 9)  # also beyond the nodes
    for given_z in (False, True):
        got = diffuse_rows(constants, xs, ys, zs, given_z)
        want = table.evaluate(xs, ys, zs if given_z else None)
        for index in range(4):
            assert_same(got[index].T, want[index])


PRIORS = {
    "none": (Priors(), False),
    "gains_scale": (Priors(0.1, 0.5), False),
    "heights": (Priors(0.1, 0.5, 0.05, 0.85, (0.6, 1.1)), False),
    "free_weights": (Priors(), True),
}


# Every (model, K, priors) but power with gains and scale free at K > 1: 16 values for 14
# unknowns, so ill-conditioned that round-off picks the path (and the solver never frees the
# power model's gains), which would compare round-off, not kernels.
_LM_CASES = [
    (model, k, priors_name)
    for model in ("correlation", "power")
    for k in (1, 4)
    for priors_name in ("none", "gains_scale", "heights")
    if not (model == "power" and priors_name == "gains_scale" and k > 1)
]


@pytest.mark.parametrize(("model", "k", "priors_name"), _LM_CASES)
def test_aggregated_fit_matches_reference(model: Model, k: int, priors_name: str) -> None:
    """A whole compiled LM run ends where the NumPy one does, after as many iterations."""
    kernel = make_kernel("paper", "heights", seed=5)
    priors, free_weights = PRIORS[priors_name]
    if priors.fits_heights:
        priors = dataclasses.replace(priors, height_mean=kernel.receiver_height)
    rng = np.random.default_rng(k)
    truth = random_state(kernel, rng, k, on_plane=True, log_scale=True)
    white = whitening_reference(model, kernel, truth, float(k))
    clean = Objective(kernel, white, np.zeros(white.weights.shape[0]), free_weights, priors)
    with use_kernels("reference"):
        # the whitened model of the truth, then back to measurement units
        modelled = -clean.residual(clean.pack(truth), truth)[: white.weights.shape[0]]
    values = unwhitened(white, modelled)
    start = dataclasses.replace(truth, positions=truth.positions + rng.uniform(-0.15, 0.15, (k, 2)))
    for damping, tol, iterations in ((1e-3, 1e-7, 40), (1e-1, 1e-4, 3)):
        with use_kernels("reference"):
            want_state, want_cost, want_used = fit_objective(
                Objective(kernel, white, values, free_weights, priors),
                start,
                max_iter=iterations,
                initial_damping=damping,
                tol=tol,
            )
        objective = Objective(kernel, white, values, free_weights, priors)
        assert objective.compiled_problem() is not None
        got_state, got_cost, got_used = fit_objective(
            objective, start, max_iter=iterations, initial_damping=damping, tol=tol
        )
        assert got_used == want_used
        assert_same(got_state.positions, want_state.positions)
        # every parameter, normwise (the noise of a noiseless fit is round-off alone)
        assert_same(objective.pack(got_state), objective.pack(want_state))
        assert got_cost == pytest.approx(want_cost, rel=1e-8, abs=1e-12 * max(1.0, want_cost))


@pytest.mark.parametrize("model", ["correlation", "power"])
def test_fit_trials_cost_what_their_gram_costs_to_the_bit(model: Model) -> None:
    """The compiled fit evaluates a trial's cost alone and builds J^T J and J^T r only at the
    trials it accepts: that cost must be the gram's to the bit (else the loop would accept
    other trials than the gram's cost does), and the normal equations the gram's, for every
    parameter count (the gram sums r^T r with another loop when it is one less than a
    multiple of four; the cost alone is evaluated for the power model only)."""
    kernel = make_kernel("paper", "heights", seed=5)
    rng = np.random.default_rng(17)
    sizes = set()
    for k in range(1, 9):
        for priors_name in ("none", "gains_scale", "heights", "free_weights"):
            priors, free_weights = PRIORS[priors_name]
            state = random_state(kernel, rng, k, on_plane=not priors.fits_heights, log_scale=True)
            white = whitening_reference(model, kernel, state, float(k))
            values = np.asarray(rng.standard_normal(white.weights.shape[0]), dtype=np.float64)
            objective = Objective(kernel, white, values, free_weights, priors)
            problem = objective.compiled_problem()
            assert problem is not None
            fields = FitModel(*problem, *objective.compiled_state(state))
            theta = objective.pack(state)
            sizes.add(theta.shape[0])
            cost, point = fit_evaluate(fields, theta)
            normal, gradient = fit_normal_equations(fields, theta, point)
            want_normal, want_gradient, want_cost = gram_kernel(*fields[:4], theta, *fields[4:])
            assert cost == want_cost
            np.testing.assert_array_equal(normal, want_normal)
            np.testing.assert_array_equal(gradient, want_gradient)
    assert {size % 4 for size in sizes} == {0, 1, 2, 3}


@pytest.fixture(scope="module")
def paper_solvers() -> dict[bool, GridlessSolver]:
    """The paper room's correlation solvers, without and with reflections in the layout (an
    interpolated diffuse table)."""
    layout = paper_layout()
    room = dataclasses.replace(
        layout.room, reflectance=Reflectance(walls=0.7, floor=0.2, ceiling=0.8)
    )
    return {
        reflecting: GridlessSolver(
            build_fingerprint(dataclasses.replace(layout, room=room) if reflecting else layout),
            "correlation",
        )
        for reflecting in (False, True)
    }


@pytest.fixture(scope="module")
def joint_kernels(paper_solvers: dict[bool, GridlessSolver]) -> dict[bool, ChannelKernel]:
    """Their channel kernels."""
    return {reflecting: solver.room.kernel for reflecting, solver in paper_solvers.items()}


@pytest.mark.parametrize("reflecting", [False, True])
def test_shape_gradients_match_reference(
    paper_solvers: dict[bool, GridlessSolver], reflecting: bool
) -> None:
    """The height and tilt derivatives behind the model-error radii (the height's from the
    compiled channel, reflections included), against the reference kernels."""
    solver = paper_solvers[reflecting]
    assert channel_constants(solver.room.kernel) is not None  # so the compiled channel runs
    rng = np.random.default_rng(13)
    positions = rng.uniform(0.0, 4.0, (5, 2))
    heights = 0.85 + rng.uniform(-0.3, 0.3, 5)
    with use_kernels("reference"):
        want = shape_gradients(solver.room, positions, heights)
    got = shape_gradients(solver.room, positions, heights)
    assert_same(got, want)
    assert np.abs(got[:, :, 0]).max() > 0.0  # the heights' column is there


@pytest.mark.parametrize("reflecting", [False, True])
@pytest.mark.parametrize("tilt_sd", [0.07, 0.0])
@pytest.mark.parametrize("k", [2, 8])
def test_joint_tolerance_model_matches_reference(
    joint_kernels: dict[bool, ChannelKernel], reflecting: bool, tilt_sd: float, k: int
) -> None:
    """The joint fit's gains (and the pieces of its Jacobian), residual and Jacobian under
    the room's tolerances (``gridless._compiled.tolerance``), on the plane and off it, at random
    tolerances in a random metric; every Jacobian column against its own magnitude."""
    kernel = joint_kernels[reflecting]
    assert (kernel.diffuse is not None) == reflecting
    rng = np.random.default_rng(100 * k + 10 * reflecting + (tilt_sd > 0))
    for on_plane in (True, False, False):
        state = random_state(kernel, rng, k, on_plane, log_scale=True)
        model = JointModel(kernel, state.heights, (0.1, 0.5), RoomTolerances(0.05, 3.0, tilt_sd))
        assert model._constants is not None
        theta = model.pack(state)
        m = kernel.n_leds
        at = 3 * k + 1
        theta[at : at + m] = rng.normal(0.0, 0.05, m)  # log amplitudes
        theta[at + m : at + 2 * m] = rng.normal(0.0, 0.3, m)  # order changes
        theta[at + 2 * m : -1] = rng.normal(0.0, 0.07, model.n_tilts)
        with use_kernels("reference"):
            white = model.whitening(theta + rng.normal(0.0, 0.01, theta.shape), state.noise)
            data = white.data(normal(rng, white.weights.shape[0]))
            want_gains, want_multipliers, want_pieces = model.gains(theta)
            want_residual, want_jacobian = model.residual_and_jacobian(theta, white, data)
        got_gains, got_multipliers, got_pieces = model.gains(theta)
        assert_same(got_gains, want_gains)
        assert_same(got_multipliers, want_multipliers)
        assert got_pieces.keys() == want_pieces.keys()
        for name, piece in want_pieces.items():
            assert_same(got_pieces[name], piece)
        got_residual, got_jacobian = model.residual_and_jacobian(theta, white, data)
        n_rows = data.shape[0] + model.prior_inverse_sd.shape[0]
        assert got_jacobian.shape == want_jacobian.shape == (n_rows, model.size())
        assert_same(got_residual, want_residual)
        for column in range(want_jacobian.shape[1]):
            assert_same(got_jacobian[:, column], want_jacobian[:, column])


@pytest.mark.parametrize("reflecting", [False, True])
@pytest.mark.parametrize("tilt_sd", [0.07, 0.0])
@pytest.mark.parametrize("k", [2, 8])
def test_joint_fit_matches_reference(
    joint_kernels: dict[bool, ChannelKernel], reflecting: bool, tilt_sd: float, k: int
) -> None:
    """A whole compiled joint LM run (``lm_kernel`` on ``joint_evaluate``) ends where the
    NumPy one (``levenberg_marquardt``) does: noisy data of tolerances the priors do not
    expect, from a start a few decimetres off, run to its stop and for two iterations."""
    kernel = joint_kernels[reflecting]
    rng = np.random.default_rng(200 * k + 10 * reflecting + (tilt_sd > 0))
    state = random_state(kernel, rng, k, on_plane=True, log_scale=True)
    model = JointModel(kernel, state.heights, (0.1, 0.5), RoomTolerances(0.05, 3.0, tilt_sd))
    truth = model.pack(state)
    m, at = kernel.n_leds, 3 * k + 1
    truth[at : at + m] = rng.normal(0.0, 0.05, m)
    truth[at + m : at + 2 * m] = rng.normal(0.0, 0.3, m)
    truth[at + 2 * m : -1] = rng.normal(0.0, 0.07, model.n_tilts)
    with use_kernels("reference"):
        white = model.whitening(truth, state.noise)
        n_data = white.weights.shape[0]
        # the whitened model of the truth (the residual of zero data is minus it), plus noise
        clean = -model.residual_and_jacobian(truth, white, np.zeros(n_data))[0][:n_data]
    data = clean + normal(rng, n_data)
    start = truth.copy()
    start[: 2 * k] += rng.uniform(-0.3, 0.3, 2 * k)
    start[at:-1] = 0.0
    for max_iter in (30, 2):
        with use_kernels("reference"):
            want, want_cost = _fit_joint(model, start, white, data, max_iter)
        assert model.compiled_model(white, data) is not None
        got, got_cost = _fit_joint(model, start, white, data, max_iter)
        assert_same(got[: 2 * k], want[: 2 * k])
        assert_same(got, want)  # every parameter, normwise
        assert got_cost == pytest.approx(want_cost, rel=1e-10)


def _grown(
    solver: GridlessSolver,
    run: Run,
    state: FitState,
    inner_iter: int,
    avoid: FloatArray | None,
) -> tuple[FitState, int]:
    """A growth step's new state and the LM iterations it used."""
    before = run.iterations
    grown = grow(solver.room, run, copy.deepcopy(state), inner_iter, avoid)
    return grown, run.iterations - before


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
@pytest.mark.parametrize("ceiling", ["none", "zero"])
def test_growth_step_is_the_python_step(layout_name: str, ceiling: str) -> None:
    """The compiled growth step (gridless.search.grow_kernel) gives the state of the
    Python step (insertion, then a short LM) to the bit with the compiled kernels it calls,
    and that of the NumPy reference kernels to 1e-10: from K = 0 to 3 targets (random
    weights, gains, scale, heights), refined or only inserted, with points to avoid
    (some, or so many that none is left) and a noise ceiling (0 when growing without
    noise)."""
    layout = LAYOUTS[layout_name]()
    fingerprint = build_fingerprint(layout)
    options = dataclasses.replace(GridlessOptions(), grow_without_noise=ceiling == "zero")
    solver = GridlessSolver(fingerprint, "correlation", options)
    python = GridlessSolver(fingerprint, "correlation", options)
    python.room.search_constants = None  # its steps run in Python
    rng = np.random.default_rng(21)
    centres = solver.room.centres
    checked = 0
    for k in range(4):
        for on_plane in (True, False):
            state = (
                random_state(solver.room.kernel, rng, k, on_plane, log_scale=True)
                if k
                else FitState.empty()
            )
            truth = random_points(solver.room.kernel, 3, rng).clip(0.1, 2.0)
            values = np.asarray(
                measurement_from_amplitudes(
                    true_amplitudes(layout, truth), "correlation", layout.n_leds
                ).values
                / solver.room.scale**2
                + 1e-3 * normal(rng, layout.n_leds * (layout.n_leds + 1) // 2),
                dtype=np.float64,
            )
            for inner_iter in (0, 2):
                for avoid in (None, centres[rng.choice(len(centres), 2)], centres):
                    run = Run(values=values, priors=solver.room.growth_priors)
                    want_run = Run(values=values, priors=python.room.growth_priors)
                    assert search_compiles(solver.room, run)
                    got, got_used = _grown(solver, run, state, inner_iter, avoid)
                    want, want_used = _grown(python, want_run, state, inner_iter, avoid)
                    assert np.array_equal(got.positions, want.positions)
                    assert got.noise == want.noise
                    assert (got_used, got.converged) == (want_used, want.converged)
                    for name in ("weights", "heights", "log_gains"):
                        assert np.array_equal(getattr(got, name), getattr(want, name))
                    assert got.log_scale == want.log_scale
                    with use_kernels("reference"):
                        reference, _ = _grown(python, want_run, state, inner_iter, avoid)
                    assert_same(got.positions, reference.positions)
                    assert_same(got.noise, reference.noise)
                    checked += 1
    assert checked == 4 * 2 * 2 * 3
    # Growth to K targets in one call (gridless.search.fit_known), the first insertion away
    # from the points to avoid: the states of the Python steps one by one.
    for n_targets in (1, 3, 6):
        for avoid in (np.zeros((0, 2)), centres[rng.choice(len(centres), 2)]):
            run = Run(values=values, priors=solver.room.growth_priors)
            want_run = Run(values=values, priors=python.room.growth_priors)
            got = grow_kernel(solver.room, run, FitState.empty(), 2, avoid, n_targets)
            want = FitState.empty()
            while want.n_targets < n_targets:
                first = want.n_targets == 0
                want = grow(python.room, want_run, want, 2, avoid if first else None)
            assert np.array_equal(got.positions, want.positions)
            assert got.noise == want.noise
            assert (run.iterations, got.converged) == (want_run.iterations, want.converged)
            for name in ("weights", "heights", "log_gains"):
                assert np.array_equal(getattr(got, name), getattr(want, name))


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
def test_refinement_is_the_python_refinement(layout_name: str) -> None:
    """The compiled whitened refinement (gridless.search.refine_kernel) gives the state of
    the Python rounds (a plug-in whitening, then LM, until a round barely moves) to the bit
    with the compiled kernels, and that of the NumPy reference kernels to 1e-10 where the
    rounds use the same iterations: K = 1 to 3 targets, one to three rounds, with the
    whitening and without (the plain metric)."""
    layout = LAYOUTS[layout_name]()
    fingerprint = build_fingerprint(layout)
    rng = np.random.default_rng(22)
    checked = 0
    for whiten in (True, False):
        options = dataclasses.replace(GridlessOptions(), whiten=whiten)
        solver = GridlessSolver(fingerprint, "correlation", options)
        python = GridlessSolver(fingerprint, "correlation", options)
        python.room.search_constants = None  # its steps run in Python
        for k in (1, 2, 3):
            for on_plane in (True, False):
                state = random_state(solver.room.kernel, rng, k, on_plane, log_scale=True)
                truth = state.positions + rng.normal(0.0, 0.1, state.positions.shape)
                values = np.asarray(
                    measurement_from_amplitudes(
                        true_amplitudes(layout, truth.clip(0.1, 2.0)), "correlation", layout.n_leds
                    ).values
                    / solver.room.scale**2
                    + 1e-3 * normal(rng, layout.n_leds * (layout.n_leds + 1) // 2),
                    dtype=np.float64,
                )
                for rounds in (1, 3):
                    run = Run(values=values, priors=solver.room.growth_priors)
                    want_run = Run(values=values, priors=python.room.growth_priors)
                    assert search_compiles(solver.room, run)
                    got = refine(solver.room, run, copy.deepcopy(state), 50, rounds)
                    want = refine(python.room, want_run, copy.deepcopy(state), 50, rounds)
                    assert np.array_equal(got.positions, want.positions)
                    assert got.noise == want.noise
                    assert (run.iterations, got.converged) == (want_run.iterations, want.converged)
                    for name in ("weights", "heights", "log_gains"):
                        assert np.array_equal(getattr(got, name), getattr(want, name))
                    assert got.log_scale == want.log_scale
                    reference_run = Run(values=values, priors=python.room.growth_priors)
                    with use_kernels("reference"):
                        reference = refine(
                            python.room, reference_run, copy.deepcopy(state), 50, rounds
                        )
                    if reference_run.iterations == run.iterations:
                        assert_same(got.positions, reference.positions)
                        # The noise is what is left of the data's energy after the model:
                        # its round-off is relative to that energy (BLAS kernels differ
                        # between CPUs), not to the small remainder.
                        energy = float(values @ values) / values.size
                        np.testing.assert_allclose(
                            got.noise, reference.noise, rtol=0.0, atol=RTOL * energy
                        )
                        checked += 1
    # Round-off may end a reference round one iteration apart; most must agree.
    assert checked >= 20


@pytest.mark.parametrize("table", TABLES)
def test_terminal_model_matches_reference(table: str) -> None:
    """A terminal looking straight up: gains and gradient at one point, free height."""
    from app.vlp.solvers.gridless.terminals import terminal_model

    kernel = make_kernel("paper", table, seed=2)
    rng = np.random.default_rng(6)
    for _ in range(3):
        theta = np.array([rng.uniform(0, 4), rng.uniform(0, 4), 0.85 + rng.uniform(-0.2, 0.2), 0])
        with use_kernels("reference"):
            want = terminal_model(kernel, theta, True, 0.85, None)
        got = terminal_model(kernel, theta, True, 0.85, None)
        for got_part, want_part in zip(got, want, strict=True):
            assert_same(got_part, want_part)


# The terminal fit's branches: (height free, photodiode normal sent, tilt fitted).
_TERMINAL_SHAPES = [
    (False, False, False),
    (True, False, False),
    (True, True, False),
    (False, True, False),
    (True, False, True),
    (False, False, True),
]


def _tilted(rng: np.random.Generator, largest: float = 0.45) -> FloatArray:
    """A unit normal whose tilt's components (tangents) are up to ``largest`` (0.45: about
    25 degrees off vertical along both)."""
    raw = np.array([rng.uniform(-largest, largest), rng.uniform(-largest, largest), 1.0])
    return np.asarray(raw / np.linalg.norm(raw), dtype=np.float64)


@pytest.mark.parametrize("layout_name", ["paper", "tilted", "beamed"])
@pytest.mark.parametrize("table", TABLES)
@pytest.mark.parametrize(("free_height", "sent_normal", "free_tilt"), _TERMINAL_SHAPES)
def test_terminal_model_kernel_matches_reference(
    layout_name: str, table: str, free_height: bool, sent_normal: bool, free_tilt: bool
) -> None:
    """Gains and gradient of every branch (straight up, a sent normal, a fitted tilt), against
    :func:`terminal_model` with the reference kernels; the tilt's columns are zero when the
    tilt is not fitted."""
    from app.vlp.solvers.gridless._compiled.terminal import terminal_model_kernel
    from app.vlp.solvers.gridless.terminals import terminal_model

    kernel = make_kernel(layout_name, table, seed=3)
    constants = channel_constants(kernel)
    assert constants is not None
    rng = np.random.default_rng(8)
    z0 = 0.85
    for _ in range(5):
        x, y = rng.uniform(-0.1, 4.1, 2)
        theta = np.array(
            [
                x,
                y,
                *([z0 + rng.uniform(-0.3, 0.3)] if free_height else []),
                *(list(rng.uniform(-0.5, 0.5, 2)) if free_tilt else []),
                rng.uniform(-0.3, 0.3),
            ]
        )
        normal = _tilted(rng) if sent_normal else None
        with use_kernels("reference"):
            want_gains, want_gradient = terminal_model(
                kernel, theta, free_height, z0, normal, free_tilt
            )
        gains, gradient = terminal_model_kernel(
            *constants,
            theta,
            (free_height, sent_normal, free_tilt, z0),
            np.zeros(3) if normal is None else normal,
        )
        assert_same(gains, want_gains)
        columns = want_gradient.shape[1]
        assert_same(gradient[:, :columns], want_gradient)
        assert not gradient[:, columns:].any()


@pytest.mark.parametrize("reflecting", [False, True])
@pytest.mark.parametrize(("free_height", "sent_normal", "free_tilt"), _TERMINAL_SHAPES)
@pytest.mark.parametrize("weighting", ["none", "scalar", "per_value"])
def test_terminal_fit_matches_reference(
    joint_kernels: dict[bool, ChannelKernel],
    reflecting: bool,
    free_height: bool,
    sent_normal: bool,
    free_tilt: bool,
    weighting: str,
) -> None:
    """One terminal's whole fit from one start (the compiled LM loop against the NumPy
    evaluation and :func:`levenberg_marquardt`): every field of the result, with
    and without priors (the gain, height and tilt pseudo-residuals), scalar and per-value
    weights; the paper room without and with reflections."""
    from app.vlp.solvers.gridless.terminals import _fit_from, terminal_model

    kernel = joint_kernels[reflecting]
    assert channel_constants(kernel) is not None  # so the compiled LM runs
    rng = np.random.default_rng(21)
    z0 = kernel.receiver_height
    priors = Priors(
        log_gain_sd=None if weighting == "none" else 0.1,
        height_sd=0.1 if free_height else 0.0,
        height_mean=z0,
        height_bounds=(z0 - 0.4, z0 + 0.4),
    )
    for _ in range(3):
        truth = rng.uniform(0.3, 3.7, 2)
        sent = _tilted(rng) if sent_normal else None
        # tilted only where the fit models it (sent, or fitted: a little, as a fit from a level
        # start can reach), so that it lands near the truth
        true_normal = (
            sent if sent is not None else _tilted(rng, 0.15) if free_tilt else np.eye(3)[2]
        )
        height = z0 + (rng.uniform(-0.2, 0.2) if free_height else 0.0)
        gains, _ = terminal_model(kernel, np.array([*truth, height, 0.0]), True, z0, true_normal)
        noise_sd = 0.01 * float(np.abs(gains).max())
        amplitudes = 1.1 * gains + noise_sd * normal(rng, gains.shape[0])
        # whitening weights near one over the noise's sd, so that data and priors both count
        weight: float | FloatArray | None = {
            "none": None,
            "scalar": 1.0 / noise_sd,
            "per_value": rng.uniform(0.5, 2.0, amplitudes.shape[0]) / noise_sd,
        }[weighting]
        start = truth + rng.uniform(-0.4, 0.4, 2)
        arguments = (kernel, amplitudes, start, z0, free_height, priors, weight, sent)
        tilt_sd = 0.2 if free_tilt else None
        with use_kernels("reference"):
            want = _fit_from(*arguments, tilt_sd)
        got = _fit_from(*arguments, tilt_sd)
        assert got.n_params == want.n_params
        assert (got.free_height, got.free_tilt) == (want.free_height, want.free_tilt)
        # every parameter, normwise, as the aggregated LM's test
        assert_same(
            np.r_[got.position, got.height, got.log_gain],
            np.r_[want.position, want.height, want.log_gain],
        )
        for name in ("normal", "jacobian", "residual"):
            assert_same(getattr(got, name), getattr(want, name))
        assert got.rss == pytest.approx(want.rss, rel=1e-8)
        assert got.cost == pytest.approx(want.cost, rel=1e-8)
        # the fit went somewhere: near the truth (a free tilt and height trade with the
        # position: 11 cm in one of these draws)
        assert np.hypot(*(got.position - truth)) < 0.2


def test_power_solves_match_reference() -> None:
    """The power model's whole solve (no eigenbasis involved) lands on the same answer."""
    layout = paper_layout()
    solver = GridlessSolver(build_fingerprint(layout), "power")
    from app.vlp.measurements import measurement_from_amplitudes
    from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions

    std = noise_std_for_snr(solver.fingerprint, 30.0)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        truth = random_positions(layout, 3, rng=rng)
        measurement = measurement_from_amplitudes(
            noisy_amplitudes(layout, truth, std, rng=rng), "power", layout.n_leds
        )
        with use_kernels("reference"):
            want = solver.solve(measurement, 3)
        got = solver.solve(measurement, 3)
        assert_same(got.positions, want.positions)
        assert got.n_iter == want.n_iter


def test_switch_selects_the_reference() -> None:
    assert kernel_mode() == "compiled"
    with use_kernels("reference"):
        assert kernel_mode() == "reference"
    assert kernel_mode() == "compiled"
    with pytest.raises(ValueError, match="kernels"), use_kernels("fast"):  # type: ignore[arg-type]
        pass


def test_dispatch_point_follows_the_switch() -> None:
    """:func:`dispatch`, the one place that chooses between a compiled kernel and its
    reference, follows :func:`use_kernels` at every call (not when a caller was built)."""

    def kernel(value: int) -> str:
        return f"kernel {value}"

    def reference(value: int) -> str:
        return f"reference {value}"

    assert dispatch(kernel, reference)(1) == "kernel 1"
    with use_kernels("reference"):
        assert dispatch(kernel, reference)(2) == "reference 2"
    assert dispatch(kernel, reference)(3) == "kernel 3"


# The solver's kernels and the tracking filter's, by the modules that hold them (both scripts
# below import them fresh).
_KERNELS_OF_A_SOLVE = """
    from app.vlp.solvers.gridless._compiled import fit
    from app.vlp.solvers.gridless._compiled.scores import correlation_scores_kernel
    from app.vlp.solvers.gridless._compiled.channel import channel_rows_kernel
    from app.vlp.solvers.gridless._compiled.uncertainty import sandwich_covariances_kernel
    from app.vlp.solvers.gridless._compiled import tolerance as joint
    from app.vlp.solvers.gridless._compiled.terminal import terminal_fit_kernel
    from app.vlp._radii_compiled import covariance_radii_kernel
    from app.vlp.solvers.gridless._compiled.search import grow_kernel, refine_kernel
    from app.vlp.tracking._filter_compiled import predict_update_kernel

    kernels = [fit.fit_kernel, fit.gram_kernel, fit.residual_kernel, fit.whitening_kernel,
               fit.whitened_data_kernel, correlation_scores_kernel, channel_rows_kernel,
               sandwich_covariances_kernel, joint.joint_gains_kernel, joint.joint_residual_kernel,
               joint.joint_fit_kernel, terminal_fit_kernel, covariance_radii_kernel,
               grow_kernel, refine_kernel, predict_update_kernel]
"""

_NO_CACHE_SCRIPT = textwrap.dedent(
    """
    import numpy as np
    import numba.core.caching as caching

    # No writable cache anywhere (as a read-only install whose home is read-only too):
    # only the NUMBA_CACHE_DIR locator is tried, and that folder cannot be created.
    caching.CacheImpl._locator_classes = [caching.UserProvidedCacheLocator]
    """
    + _KERNELS_OF_A_SOLVE
    + """
    from app.vlp._kernels import use_kernels
    from app.vlp.radii import confidence_radii

    # the fallback: every kernel is compiled without a disk cache
    assert all(type(k._cache).__name__ == "NullCache" for k in kernels)
    assert all(len(k.signatures) == 0 for k in kernels)
    # one compiled in memory here gives its reference's numbers
    covariances = np.array([[[0.01, 0.002], [0.002, 0.004]], [[2e-4, 0.0], [0.0, 3e-3]]])
    got = confidence_radii(covariances)
    with use_kernels("reference"):
        want = confidence_radii(covariances)
    assert len(covariance_radii_kernel.signatures) == 1
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=0.0)
    print("ok")
    """
)

_WARM_UP_SCRIPT = textwrap.dedent(
    """
    import numpy as np

    from app.vlp.fingerprints import build_fingerprint
    from app.vlp.measurements import measurement_from_amplitudes
    from app.vlp.presets import paper_layout
    from app.vlp.simulation import noisy_amplitudes, true_amplitudes
    from app.vlp.solvers import warm_up
    from app.vlp.solvers.gridless import GridlessSolver
    from app.vlp.tracking import Tracks, TrackerSettings, step_anonymous, step_labelled
    """
    + _KERNELS_OF_A_SOLVE
    + """
    assert all(len(k.signatures) == 0 for k in kernels)
    warm_up()
    before = [len(k.signatures) for k in kernels]
    assert all(count >= 1 for count in before), before
    layout = paper_layout()
    fingerprint = build_fingerprint(layout)
    truth = np.array([[0.93, 1.41], [2.72, 3.05]])
    for model in ("correlation", "power"):
        solver = GridlessSolver(fingerprint, model)
        measurement = measurement_from_amplitudes(true_amplitudes(layout, truth), model, 16)
        solution = solver.solve(measurement, 2)
        order = np.argsort(solution.positions[:, 0])
        assert np.allclose(solution.positions[order], truth, atol=1e-3), solution.positions
    amplitudes = noisy_amplitudes(layout, truth, 1e-9, rng=1)
    found = GridlessSolver(fingerprint, "correlation").solve_terminals(amplitudes)
    assert np.allclose(found.positions, truth, atol=1e-3), found.positions
    # a labelled and an anonymous tracker, each started by one solve and moved by the next
    fix_covariances = np.tile(1e-4 * np.eye(2), (2, 1, 1))
    settings = TrackerSettings()
    labelled, anonymous = Tracks.empty(), Tracks.empty()
    for time_s, rows in ((0.0, np.array([-1, -1])), (0.2, np.array([0, 1]))):
        fixes = truth + 0.1 * time_s
        labelled = step_labelled(labelled, rows, fixes, fix_covariances, time_s, settings).tracks
        anonymous = step_anonymous(anonymous, fixes, fix_covariances, time_s, settings).tracks
    assert np.all(labelled.updates == 2) and np.all(anonymous.updates == 2)
    after = [len(k.signatures) for k in kernels]
    # warm_up compiled (or loaded) every signature a solve and a tracker's step use: nothing
    # was compiled during the solves and the steps
    assert after == before, (before, after)
    print("ok")
    """
)


def _run_script(script: str, env: dict[str, str]) -> None:
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("ok")


@pytest.mark.slow
def test_works_without_a_writable_cache(tmp_path: Path) -> None:
    """Pointing NUMBA_CACHE_DIR at a place that cannot be written (below a regular file:
    not even root can make that folder): every kernel falls back to compiling in memory, and
    one compiled so gives its reference's numbers. (Compiling the others in memory too would
    take a minute and check numba, not this fallback.)"""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(blocker / "cache"), VLP_KERNELS="compiled")
    _run_script(_NO_CACHE_SCRIPT, env)
    assert not (blocker / "cache").exists()


@pytest.mark.slow
def test_warm_up_compiles_every_signature_a_solve_uses() -> None:
    """In a fresh interpreter (its kernels from the disk cache that ./test's warm-up fills),
    warm_up gives every kernel the signatures that the solves of both models, a terminals'
    solve and the steps of both trackers then use: none is compiled at a request or a
    step."""
    _run_script(_WARM_UP_SCRIPT, dict(os.environ, VLP_KERNELS="compiled"))


def test_the_disk_cache_is_keyed_by_every_science_source(tmp_path: Path) -> None:
    """numba keys a cached kernel by its own file; a change in a file it calls must still
    compile it afresh: the cache folder is named after all of app/vlp's sources."""
    sources = tmp_path / "vlp"
    (sources / "solvers").mkdir(parents=True)
    (sources / "channel.py").write_text("A = 1\n")
    (sources / "solvers" / "kernel.py").write_text("B = 2\n")
    base = tmp_path / "cache"
    first = kernel_cache_dir(base, sources)
    assert first.parent == base and first.name.startswith("vlp-")
    assert kernel_cache_dir(base, sources) == first  # same sources, same folder
    (sources / "channel.py").write_text("A = 3\n")  # only the callee's file changes
    changed = kernel_cache_dir(base, sources)
    assert changed != first
    (sources / "channel.py").write_text("A = 1\n")
    assert kernel_cache_dir(base, sources) == first
    (sources / "solvers" / "kernel.py").rename(sources / "solvers" / "moved.py")
    assert kernel_cache_dir(base, sources) != first  # a renamed file counts too
    # In this process, the kernels' cache lives in the folder of the real sources.
    science = Path(__file__).resolve().parents[3] / "app" / "vlp"
    folder = Path(importlib.import_module("numba.core.config").CACHE_DIR)
    assert folder == kernel_cache_dir(folder.parent, science)
    cache_path = Path(channel_rows_kernel._cache._cache_path)  # type: ignore[attr-defined]
    assert folder in cache_path.parents


def test_warm_up_is_idempotent() -> None:
    warm_up()
    warm_up()


def test_sparse_products_are_the_dense_ones() -> None:
    """Long, mostly zero rows (a large room's Jacobian) take the sparse product, which
    equals ``rows @ rows.T`` to round-off; short or dense rows are left to the dense one."""
    rng = np.random.default_rng(17)
    rows = np.zeros((40, 600))
    for i in range(38):  # a few nonzeros each, in a band (a target's nearby LEDs)
        start = int(rng.integers(0, 580))
        rows[i, start : start + 12] = rng.standard_normal(12) * (rng.random(12) < 0.7)
    rows[38] = rng.standard_normal(600)  # the noise coefficient's and residual's rows: dense
    rows[39] = rng.standard_normal(600)
    rows[5] = 0.0  # an all-zero row (a target out of every LED's view)
    product, sparse = _sparse_symmetric_product(rows)
    assert sparse
    np.testing.assert_allclose(product, rows @ rows.T, rtol=1e-12, atol=1e-12)
    assert not _sparse_symmetric_product(rows[:, :100])[1]  # short rows
    assert not _sparse_symmetric_product(rng.standard_normal((6, 600)))[1]  # dense rows


def test_large_room_grams_match_the_reference() -> None:
    """``J^T J``, ``J^T r`` and the cost of a 40 m hall's power fit (144 LEDs, each target
    sees about a tenth of them: the sparse product), plain and whitened."""
    leds = tuple(
        Led(x=3.2 * (i + 0.5), y=3.2 * (j + 0.5), z=3.0) for i in range(12) for j in range(12)
    )
    layout = Layout(Room(40.0, 40.0, 3.0), Grid(0.1, 0.85), leds, Receiver(fov_deg=70.0))
    rng = np.random.default_rng(23)
    k = 12
    positions = rng.uniform(1.0, 39.0, (k, 2))
    # Normalised as the solver does: gains of order one where a target sees an LED.
    raw = ChannelKernel(layout, 1.0).gains_xy(positions[:, 0], positions[:, 1])
    kernel = ChannelKernel(layout, float(np.sqrt(np.mean(raw[raw > 0] ** 2))))
    state = FitState(positions, np.ones(k), 1e-3, np.full(k, 0.85), np.zeros(k))
    for white in (
        Whitening.identity("power", kernel.n_leds),
        whitening_reference("power", kernel, state, float(k)),
    ):
        values = normal(rng, kernel.n_leds)
        objective = Objective(kernel, white, values, False, Priors())
        theta = objective.pack(state)
        with use_kernels("reference"):
            want = gram_reference(objective, theta, state)
            assert _sparse_symmetric_product(objective.augmented(theta, state))[1]
        fresh = Objective(kernel, white, values, False, Priors())
        for got_part, want_part in zip(gram(fresh, theta, state), want, strict=True):
            assert_same(got_part, want_part)


# As _LM_CASES, on and off the receivers' plane, with free weights too; power with free
# multipliers at K > 1 (gains and scale, or weights: each nearly the noise atom's direction,
# the normal matrix ill-conditioned) would compare round-off (seen: 7e-10), not kernels.
_UNCERTAINTY_CASES = [
    (model, k, priors_name, on_plane)
    for model in ("correlation", "power")
    for k in (1, 3)
    for priors_name in PRIORS
    for on_plane in (True, False)
    if not (model == "power" and priors_name in ("gains_scale", "free_weights") and k > 1)
]


@pytest.mark.parametrize(("model", "k", "priors_name", "on_plane"), _UNCERTAINTY_CASES)
def test_uncertainty_matches_reference(
    model: Model, k: int, priors_name: str, on_plane: bool
) -> None:
    """The compiled model-error sandwich (``gridless._compiled.uncertainty``) gives the NumPy path's
    covariances and fit quality, whitened or not, with a reflection table, and with the
    tilt's columns left out for a layout whose photodiodes are level."""
    layout = paper_layout()
    solver = GridlessSolver(build_fingerprint(layout), model)
    # The solver's normalisation (gains of order one), diffuse gains a tenth of the direct.
    scale = solver.room.scale
    magnitude = 0.1 * scale / layout.leds[0].pilot_amplitude
    table = synthetic_table(layout, True, seed=k, magnitude=magnitude)
    kernel = solver.room.kernel = ChannelKernel(layout, scale, table)
    priors, free_weights = PRIORS[priors_name]
    if priors.fits_heights:
        priors = dataclasses.replace(priors, height_mean=kernel.receiver_height)
    rng = np.random.default_rng(100 + 10 * k + len(priors_name))
    state = random_state(kernel, rng, k, on_plane, log_scale=True)
    if free_weights:
        state = dataclasses.replace(state, log_gains=np.zeros(k), log_scale=0.0)
    for white, level in itertools.product(
        (
            Whitening.identity(model, kernel.n_leds),
            whitening_reference(model, kernel, state, float(k)),
        ),
        (False, True),
    ):
        solver.room.receivers_level = level
        values = normal(rng, white.weights.shape[0])
        objective = Objective(kernel, white, values, free_weights, priors)
        assert objective.compiled_problem() is not None
        with use_kernels("reference"):
            want, want_fit = sandwich_covariances(solver.room, objective, state)
        got, got_fit = sandwich_covariances(solver.room, objective, state)
        assert got.shape == (k, 2, 2)
        # Each kernel of the chain agrees to 1e-10 on the same inputs (tests below), but
        # the chain amplifies round-off: in the whitened K = 3 free-weights state the two
        # normal matrices (a loop here, BLAS there) differ by 1e-16 and the model-error
        # variances of the reweighted non-negative fit, on nearly collinear leverages, by
        # 1e-10 (5e-10 in the covariances on one AMD EPYC machine; below 1e-10 on those
        # before it). The data's own round-off moves the reference by only 1e-13.
        assert_same(got, want, rtol=CHAIN_RTOL)
        assert got_fit.chi2_per_dof == pytest.approx(want_fit.chi2_per_dof, rel=1e-10)
        assert (got_fit.dof, got_fit.quality) == (want_fit.dof, want_fit.quality)


def test_misfit_design_matches_reference() -> None:
    """Random Jacobians and error columns, a kind wider than the data (the other Gram
    matrix of its spread) and a singular normal matrix (the pseudo-inverse's cut-off)."""
    rng = np.random.default_rng(31)
    for n_data, n_params, widths in ((40, 6, (5, 50, 1)), (12, 4, (3,)), (9, 9, (2, 20))):
        jacobian = rng.standard_normal((n_data, n_params))
        jacobian[:, -1] = jacobian[:, 0] if n_data == 9 else jacobian[:, -1]  # rank-deficient
        prior = np.diag(rng.uniform(0.0, 1.0, n_params)) * (n_data != 9)
        normal_matrix = jacobian.T @ jacobian + prior
        columns = [rng.standard_normal((n_data, width)) for width in widths]
        want = misfit_design_reference(jacobian, normal_matrix, columns)
        got = misfit_design_kernel(
            jacobian, normal_matrix, np.hstack(columns), np.array(widths, dtype=np.int64)
        )
        # The priors' information is a difference of normal matrices: round-off of theirs.
        assert_same(got[2] + normal_matrix, want.prior_normal + normal_matrix)
        for got_part, want_part in zip(
            got[:2] + got[3:],
            (
                want.inverse,
                want.data_normal,
                want.error_normals,
                want.noise_leverage,
                want.error_leverages,
                want.error_spread,
            ),
            strict=True,
        ):
            assert_same(got_part, want_part)


def test_nnls_matches_scipy() -> None:
    """Lawson-Hanson: the solution of ``scipy.optimize.nnls`` on random problems (some
    with every variable, some with none, at the bound)."""
    rng = np.random.default_rng(37)
    for trial in range(200):
        n_rows, n = int(rng.integers(1, 30)), int(rng.integers(1, 6))
        matrix = rng.standard_normal((n_rows, n)) * rng.uniform(0.1, 10.0, n)
        target = rng.standard_normal(n_rows) + (trial % 3) * matrix @ rng.uniform(0.0, 1.0, n)
        want, _ = optimize.nnls(matrix, target)
        assert_same(nnls_kernel(matrix, target), want)


def test_nnls_with_columns_orders_of_magnitude_apart() -> None:
    """Columns 10^-25 to 1 in size, some rows reached only by the tiny ones (a power fit's
    model-error columns next to its noise column, from a random room that answered 500 with
    a division by zero): the optimum of ``scipy.optimize.nnls``, column by column relative to
    its own size, and the same least-squares cost."""
    rng = np.random.default_rng(43)
    for trial in range(100):
        n_rows, n = int(rng.integers(4, 12)), int(rng.integers(2, 5))
        matrix = rng.uniform(0.0, 1.0, (n_rows, n)) * 10.0 ** rng.uniform(-25.0, 0.0, n)
        matrix[: n_rows // 2, 1:] *= 1e-8  # the big column dominates the first rows
        matrix[n_rows // 2 :, 0] = 0.0  # and does not reach the others
        target = rng.uniform(0.0, 2.0, n_rows) * (1.0 + (trial % 2) * 1e3)
        want, want_norm = optimize.nnls(matrix, target)
        got = nnls_kernel(matrix, target)
        assert np.all(got >= 0.0)
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=0.0)
        assert np.linalg.norm(matrix @ got - target) == pytest.approx(want_norm, rel=1e-10)


@pytest.mark.parametrize("max_noise", [1.0, 1e-3])
def test_fit_misfit_matches_reference(max_noise: float) -> None:
    """Noise and model-error variances and their degrees of freedom (a zero kind too; the
    noise at its bound with the small ``max_noise``)."""
    rng = np.random.default_rng(41)
    n_data = 50
    noise_leverage = rng.uniform(0.5, 1.0, n_data)
    error_leverages = rng.uniform(0.0, 2.0, (n_data, 3)) * np.array([1.0, 0.1, 0.0])
    spread = np.array([30.0, 2.0, 0.0])
    residual = rng.standard_normal(n_data) * np.sqrt(noise_leverage + 0.3 * error_leverages[:, 0])
    design = MisfitDesign(
        np.eye(2),
        np.eye(2),
        np.zeros((2, 2)),
        np.zeros((3, 2, 2)),
        noise_leverage,
        error_leverages,
        spread,
    )
    want = fit_misfit([design], [residual], max_noise=max_noise)
    noise, model_errors, dofs = fit_misfit_kernel(
        residual, noise_leverage, error_leverages, spread, max_noise
    )
    assert noise == pytest.approx(want.noise, rel=1e-10)
    assert_same(model_errors, want.model_errors)
    assert_same(dofs, want.dofs)


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
def test_aggregated_profiles_match_reference(layout_name: str) -> None:
    """An answer's far-place profiles (gridless.report.profiles, correlation model)."""
    layout = LAYOUTS[layout_name]()
    solver = GridlessSolver(build_fingerprint(layout), "correlation")
    rng = np.random.default_rng(12)
    state = random_state(solver.room.kernel, rng, 3, on_plane=False, log_scale=True)
    values = normal(rng, layout.n_leds * (layout.n_leds + 1) // 2)
    run = Run(values=values, priors=solver.room.priors)
    # Each mode whitens on its own: the eigenbasis of the unlit directions' repeated
    # eigenvalue is round-off's choice, and the metric must not depend on it.
    with use_kernels("reference"):
        want = profiles(solver.room, run, state)
    got = profiles(solver.room, run, state)
    for got_part, want_part in zip(got, want, strict=True):
        assert_same(got_part, want_part)
