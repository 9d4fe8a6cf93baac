"""Example arguments of every row of the kernel table (:mod:`._kernel_table`), and the parts
of an answer that a row compares where an answer holds more than its meaning fixes.

Each examples function builds fresh, seeded arguments at every call (a parity test gives
the reference and the kernel one set each), of the types a solve passes, so that
:func:`app.vlp.solvers.warm_up` compiles what the requests use.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import itertools
import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy import special

from ..fingerprints import Fingerprint, build_fingerprint
from ..measurements import Model
from ..presets import paper_layout
from ._kernel_rooms import LAYOUTS, TABLES, make_kernel
from .gridless.channel import ChannelKernel
from .gridless.fitting import Run
from .gridless.joint_model import (
    JointModel,
    RoomTolerances,
    joint_residual_reference,
)
from .gridless.lm import MAX_REJECTIONS, STEP_TOL_M, LMSettings
from .gridless.local import (
    PowerScan,
)
from .gridless.model import (
    Objective,
    residual_reference,
)
from .gridless.options import GridlessOptions
from .gridless.room import PreparedRoom
from .gridless.solver import GridlessSolver
from .gridless.state import FitState, Priors
from .gridless.terminals import (
    terminal_fit_arguments,
    terminal_model,
)
from .gridless.tolerances import JOINT_LM
from .gridless.whitening import (
    Whitening,
    whitening_reference,
)

__all__ = [
    "Arguments",
    "best_of_tiles_examples",
    "channel_rows_examples",
    "channel_rows_parts",
    "correlation_profiles_examples",
    "correlation_scores_examples",
    "covariance_radii_examples",
    "escape_test_examples",
    "fit_examples",
    "grow_examples",
    "joint_examples",
    "joint_fit_examples",
    "joint_gains_examples",
    "joint_gains_parts",
    "misfit_design_examples",
    "objective_examples",
    "profile_cells_examples",
    "refine_examples",
    "sandwich_examples",
    "sandwich_parts",
    "search_parts",
    "squared_gains_dot_examples",
    "terminal_fit_examples",
    "whitened_data_examples",
    "whitening_examples",
    "whitening_metric",
]

Arguments = tuple[Any, ...]
_MODELS: tuple[Model, ...] = ("correlation", "power")


def _kernel() -> ChannelKernel:
    return ChannelKernel(paper_layout(), 1.0)


def random_state(
    kernel: ChannelKernel,
    rng: np.random.Generator,
    k: int,
    on_plane: bool = True,
    log_scale: bool = False,
) -> FitState:
    """A random state of ``k`` targets on the receiver plane (or up to 0.2 m off it), its
    common log scale 0 (or random, drawn last)."""
    length, width = kernel.bounds
    positions = np.column_stack(
        (rng.uniform(0.2, length - 0.2, k), rng.uniform(0.2, width - 0.2, k))
    )
    heights = np.full(k, kernel.receiver_height)
    if not on_plane:
        heights = heights + rng.uniform(-0.2, 0.2, k)
    return FitState(
        positions,
        rng.uniform(0.5, 1.5, k),
        float(rng.uniform(1e-4, 1e-2)),
        heights,
        rng.uniform(-0.2, 0.2, k),
        float(rng.uniform(-0.3, 0.3)) if log_scale else 0.0,
    )


def _priors(kernel: ChannelKernel) -> list[tuple[Priors, bool]]:
    """``(priors, free_weights)`` of every parameter layout: positions only, gains and
    scale, heights too, free weights."""
    height = kernel.receiver_height
    return [
        (Priors(), False),
        (Priors(0.1, 0.5), False),
        (Priors(0.1, 0.5, 0.05, height, (height - 0.25, height + 0.25)), False),
        (Priors(), True),
    ]


def _whitenings(kernel: ChannelKernel, rng: np.random.Generator) -> list[Whitening]:
    """Both models' metrics at a random two-target state, and the correlation model's
    plain metric (the search's)."""
    state = random_state(kernel, rng, 2)
    return [
        whitening_reference("correlation", kernel, state, 2.0),
        whitening_reference("power", kernel, state, 2.0),
        Whitening.identity("correlation", kernel.n_leds),
    ]


def whitened_data_examples() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(8)
    return [
        (white, rng.standard_normal(white.weights.shape[0])) for white in _whitenings(kernel, rng)
    ]


def _gains(kernel: ChannelKernel, rng: np.random.Generator, n_points: int) -> np.ndarray:
    """Line-of-sight gains (M, n_points) of random points of the room."""
    length, width = kernel.bounds
    xs = rng.uniform(0.0, length, n_points)
    ys = rng.uniform(0.0, width, n_points)
    return np.ascontiguousarray(kernel.gains_xy(xs, ys))


def _dense_room(gains: np.ndarray) -> Any:
    """The fields of a dense room that the correlation scores read."""
    return SimpleNamespace(
        fingerprint=SimpleNamespace(n_leds=gains.shape[0]), dense=True, gains=gains
    )


def correlation_scores_examples() -> list[Arguments]:
    """Every layout's dense room of 30 points, in the plain and a plug-in metric."""
    rng = np.random.default_rng(11)
    examples: list[Arguments] = []
    for name in LAYOUTS:
        kernel = make_kernel(name, "none")
        room = _dense_room(_gains(kernel, rng, 30))
        for white in _whitenings(kernel, rng):
            if white.model == "correlation":
                examples.append((room, white, rng.standard_normal(white.weights.shape[0])))
    return examples


def correlation_profiles_examples() -> list[Arguments]:
    kernel = _kernel()
    rng = np.random.default_rng(12)
    gains = _gains(kernel, rng, 30)
    examples = []
    for white in _whitenings(kernel, rng):
        if white.model != "correlation":
            continue
        for k in (1, 3):
            examples.append(
                (
                    white,
                    rng.standard_normal(white.weights.shape[0]),
                    gains,
                    _gains(kernel, rng, k),
                    rng.uniform(0.5, 1.5, k),
                )
            )
    return examples


def objective_examples() -> list[Arguments]:
    """``(objective, theta, state)``: every layout, without a reflection table and with one
    around the plane; both models, K = 1 and 3, every parameter layout, on the plane and off
    it, in the plain and the plug-in metric, theta near the state's."""
    rng = np.random.default_rng(13)
    examples = []
    kernels = [
        make_kernel(name, table, seed=3) for name in LAYOUTS for table in ("none", "heights")
    ]
    for kernel, model, k, on_plane in itertools.product(kernels, _MODELS, (1, 3), (True, False)):
        for priors, free_weights in _priors(kernel):
            state = random_state(kernel, rng, k, on_plane)
            for white in (
                Whitening.identity(model, kernel.n_leds),
                whitening_reference(model, kernel, state, float(k)),
            ):
                values = rng.standard_normal((white.weights.shape[0],))
                objective = Objective(kernel, white, values, free_weights, priors)
                theta = objective.pack(state)
                examples.append((objective, theta + rng.normal(0.0, 0.01, theta.shape), state))
    return examples


def fit_examples() -> list[Arguments]:
    """``fit_objective``'s LM runs: noisy data of a random truth, from a start a few
    centimetres off, to the stop and for three iterations; both models, K = 1 and 3, every
    parameter layout but the power model's free gains and scale at K > 1 (nearly the noise
    atom's direction: round-off would choose the path)."""
    kernel = _kernel()
    rng = np.random.default_rng(14)
    examples = []
    for model, k, (priors, free_weights) in itertools.product(_MODELS, (1, 3), _priors(kernel)):
        if model == "power" and k > 1 and (free_weights or priors.fits_gains):
            continue
        truth = random_state(kernel, rng, k)
        white = whitening_reference(model, kernel, truth, float(k))
        clean = Objective(kernel, white, np.zeros(white.weights.shape[0]), free_weights, priors)
        # the whitened model of the truth is minus the residual of zero data; the data in
        # measurement units are that over the weights, rotated back
        modelled = -residual_reference(clean, clean.pack(truth), truth)[: white.weights.shape[0]]
        values = unwhitened(white, modelled) * (1.0 + 0.01 * rng.standard_normal(modelled.shape))
        objective = Objective(kernel, white, values, free_weights, priors)
        start = dataclasses.replace(
            truth, positions=truth.positions + rng.uniform(-0.1, 0.1, (k, 2))
        )
        lower, upper = objective.bounds(k)
        for max_iter, damping, tol in ((40, 1e-3, 1e-7), (3, 1e-1, 1e-4)):
            settings = LMSettings(max_iter, damping, MAX_REJECTIONS, tol, STEP_TOL_M, 2 * k, True)
            examples.append((objective, start, objective.pack(start), lower, upper, settings))
    return examples


def unwhitened(white: Whitening, whitened: np.ndarray) -> np.ndarray:
    """The measurement whose whitening is ``whitened``."""
    plain = whitened / white.weights
    if white.rotation is None:
        return plain
    n_leds = white.n_leds
    full = np.zeros((n_leds, n_leds))
    full[white.upper, white.lower] = plain
    full[white.lower, white.upper] = plain
    back = white.rotation @ full @ white.rotation.T
    return np.asarray(back[white.upper, white.lower])


def channel_rows_examples() -> list[Arguments]:
    """Every layout, with no reflection table and with both kinds: one point and seven, some
    beyond the walls (the table clamps, the line of sight does not), on the plane and at
    heights around it."""
    rng = np.random.default_rng(16)
    examples = []
    for layout_name, table, n_points, on_plane in itertools.product(
        LAYOUTS, TABLES, (1, 7), (True, False)
    ):
        kernel = make_kernel(layout_name, table)
        length, width = kernel.bounds
        xs = rng.uniform(-0.2, length + 0.2, n_points)
        ys = rng.uniform(-0.2, width + 0.2, n_points)
        zs = kernel.receiver_height + rng.uniform(-0.25, 0.25, n_points)
        examples.append((kernel, xs, ys, zs, on_plane))
    return examples


def whitening_examples() -> list[Arguments]:
    """``(model, kernel, state, n_terminals)``: every layout (with a reflection table on the
    plane), both models, K = 1, 3 and 20, on the plane and off it."""
    rng = np.random.default_rng(15)
    examples: list[Arguments] = []
    for name in LAYOUTS:
        kernel = make_kernel(name, "flat", seed=4)
        for model, k, on_plane in itertools.product(_MODELS, (1, 3, 20), (True, False)):
            examples.append((model, kernel, random_state(kernel, rng, k, on_plane), float(k)))
    return examples


def channel_rows_parts(rows: np.ndarray) -> tuple[Any, ...]:
    """The gains and each derivative, each against its own magnitude."""
    return tuple(rows)


def whitening_metric(white: Whitening) -> tuple[Any, ...]:
    """A whitening's weights and its metric ``U diag(lam) U^T`` (eigenvectors themselves
    are not unique: signs, and any basis of the noise-only eigenspace)."""
    if white.rotation is None:
        return (white.weights, np.zeros((0, 0)))
    diagonal = white.upper == white.lower  # weight^-2 there is 4 sigma^2 lam
    return (white.weights, (white.rotation * white.weights[diagonal] ** -2.0) @ white.rotation.T)


def misfit_design_examples() -> list[Arguments]:
    rng = np.random.default_rng(31)
    examples = []
    for n_data, n_params, widths in ((40, 6, (5, 50, 1)), (12, 4, (3,))):
        jacobian = rng.standard_normal((n_data, n_params))
        normal = jacobian.T @ jacobian + np.diag(rng.uniform(0.0, 1.0, n_params))
        examples.append(
            (jacobian, normal, [rng.standard_normal((n_data, width)) for width in widths])
        )
    return examples


def _by_cell(rng: np.random.Generator, n_cells: int, n_leds: int) -> sp.csr_array:
    """A sparse ``G^T`` (cells x LEDs), about half of it zero."""
    dense = rng.uniform(0.0, 2.0, (n_cells, n_leds)) * (rng.uniform(size=(n_cells, n_leds)) < 0.5)
    return sp.csr_array(dense)


def squared_gains_dot_examples() -> list[Arguments]:
    rng = np.random.default_rng(21)
    by_cell = _by_cell(rng, 12, 16)
    return [(by_cell, 0.5, rng.standard_normal(16), fourth) for fourth in (False, True)]


def best_of_tiles_examples() -> list[Arguments]:
    """Tiles of a 5 x 4 grid in 2 x 2 tiles (the last row and column partial)."""
    rng = np.random.default_rng(22)
    n_x, n_y, n_leds = 5, 4, 16
    by_cell = _by_cell(rng, n_x * n_y, n_leds)
    squared = by_cell.power(2)
    fourth_sums = np.asarray(squared.power(2).sum(axis=1), dtype=np.float64)
    scan = PowerScan(n_y, n_x, 2, 1.0, sp.csr_array((6, n_leds)), np.zeros(6), fourth_sums, by_cell)
    return [
        (scan, np.array(tiles, dtype=np.int64), rng.standard_normal(n_leds), weight, 1.5)
        for tiles, weight in (([0], 1.0), ([5, 2, 3], 0.7), ([0, 1, 2, 3, 4, 5], 2.0))
    ]


def _tilted(rng: np.random.Generator, largest: float) -> np.ndarray:
    """A unit normal whose tilt's components (tangents) are up to ``largest``."""
    raw = np.array([rng.uniform(-largest, largest), rng.uniform(-largest, largest), 1.0])
    return np.asarray(raw / np.linalg.norm(raw))


def terminal_fit_examples() -> list[Arguments]:
    """One terminal's fit from a start up to 0.4 m off, every branch (height free or not; a
    photodiode normal sent, a tilt fitted, or neither), without priors and with scalar and
    per-value weights: noisy amplitudes of a random truth (tilted only where the fit
    models it, so that it lands near the truth)."""
    kernel = _kernel()
    rng = np.random.default_rng(21)
    z0 = kernel.receiver_height
    shapes = (  # (height free, normal sent, tilt fitted)
        (False, False, False),
        (True, False, False),
        (True, True, False),
        (False, True, False),
        (True, False, True),
        (False, False, True),
    )
    examples = []
    for (free_height, sent_normal, free_tilt), weighting in itertools.product(
        shapes, ("none", "scalar", "per_value")
    ):
        priors = Priors(
            log_gain_sd=None if weighting == "none" else 0.1,
            height_sd=0.1 if free_height else 0.0,
            height_mean=z0,
            height_bounds=(z0 - 0.4, z0 + 0.4),
        )
        truth = rng.uniform(0.3, 3.7, 2)
        sent = _tilted(rng, 0.45) if sent_normal else None
        true_normal = sent if sent is not None else _tilted(rng, 0.15) if free_tilt else None
        height = z0 + (rng.uniform(-0.2, 0.2) if free_height else 0.0)
        gains, _ = terminal_model(kernel, np.array([*truth, height, 0.0]), True, z0, true_normal)
        noise_sd = 0.01 * float(np.abs(gains).max())
        amplitudes = 1.1 * gains + noise_sd * rng.standard_normal(gains.shape[0])
        weight = {
            "none": None,
            "scalar": 1.0 / noise_sd,
            "per_value": rng.uniform(0.5, 2.0, amplitudes.shape[0]) / noise_sd,
        }[weighting]
        start = truth + rng.uniform(-0.4, 0.4, 2)
        tilt_sd = 0.2 if free_tilt else None
        examples.append(
            terminal_fit_arguments(
                kernel, amplitudes, start, z0, free_height, priors, weight, sent, tilt_sd
            )
        )
    return examples


def _joint_model(
    kernel: ChannelKernel, rng: np.random.Generator, k: int, tilt_sd: float, on_plane: bool
) -> tuple[JointModel, FitState, np.ndarray]:
    """A joint model of ``k`` random targets, its state and a theta of random tolerances."""
    state = random_state(kernel, rng, k, on_plane)
    model = JointModel(kernel, state.heights, (0.1, 0.5), RoomTolerances(0.05, 3.0, tilt_sd))
    theta = model.pack(state)
    m, at = kernel.n_leds, 3 * k + 1
    theta[at : at + m] = rng.normal(0.0, 0.05, m)  # log amplitudes
    theta[at + m : at + 2 * m] = rng.normal(0.0, 0.3, m)  # order changes
    theta[at + 2 * m : -1] = rng.normal(0.0, 0.07, model.n_tilts)  # tilts
    return model, state, theta


def joint_examples() -> list[Arguments]:
    """``(model, theta, white, data)`` of the joint fit: K = 2 and 8, with and without
    tilts, on the plane and off it, random data in a metric near theta's."""
    kernel = _kernel()
    rng = np.random.default_rng(18)
    examples = []
    for k, tilt_sd, on_plane in itertools.product((2, 8), (0.07, 0.0), (True, False)):
        model, state, theta = _joint_model(kernel, rng, k, tilt_sd, on_plane)
        white = model.whitening(theta + rng.normal(0.0, 0.01, theta.shape), state.noise)
        data = white.data(np.asarray(rng.standard_normal(white.weights.shape[0]), dtype=np.float64))
        examples.append((model, theta, white, data))
    return examples


def joint_gains_examples() -> list[Arguments]:
    return [(model, theta) for model, theta, _, _ in joint_examples()]


_JOINT_PIECES = ("slopes", "amplitude_part", "order_part", "tilt_x", "tilt_y")


def joint_gains_parts(answer: Any) -> tuple[Any, ...]:
    """The gains, the multipliers and every piece of the Jacobian, by name."""
    gains, multipliers, pieces = answer
    assert set(pieces) == set(_JOINT_PIECES)
    return (gains, multipliers, *(pieces[name] for name in _JOINT_PIECES))


def joint_fit_examples() -> list[Arguments]:
    """The joint LM run on noisy data of tolerances the priors do not expect, from a start
    a few decimetres off, to its stop and for two iterations."""
    kernel = _kernel()
    rng = np.random.default_rng(19)
    examples = []
    for k, tilt_sd in itertools.product((2, 8), (0.07, 0.0)):
        model, state, truth = _joint_model(kernel, rng, k, tilt_sd, True)
        white = model.whitening(truth, state.noise)
        n_data = white.weights.shape[0]
        # the whitened model of the truth (the residual of zero data is minus it), plus noise
        clean = -joint_residual_reference(model, truth, white, np.zeros(n_data))[0][:n_data]
        data = clean + rng.standard_normal(n_data)
        start = truth.copy()
        start[: 2 * k] += rng.uniform(-0.3, 0.3, 2 * k)
        start[3 * k + 1 : -1] = 0.0
        lower, upper = model.bounds()
        for max_iter in (30, 2):
            settings = JOINT_LM._replace(max_iter=max_iter)
            examples.append((model, start, white, data, lower, upper, settings))
    return examples


@functools.cache
def _paper_fingerprint() -> Fingerprint:
    return build_fingerprint(paper_layout())


def sandwich_examples() -> list[Arguments]:
    """``(room, objective, state)`` of the paper room's solvers: both models, K = 1 and 3,
    every parameter layout (but the power model's free multipliers at K > 1: nearly the
    noise atom's direction, ill-conditioned enough that round-off would be compared), on
    the plane and off it, plain and plug-in metrics, the photodiodes level or not."""
    fingerprint = _paper_fingerprint()
    rng = np.random.default_rng(20)
    examples = []
    for model in _MODELS:
        room = GridlessSolver(fingerprint, model).room
        kernel = room.kernel
        levelled = copy.copy(room)
        levelled.receivers_level = not room.receivers_level
        for k, (priors, free_weights), on_plane in itertools.product(
            (1, 3), _priors(kernel), (True, False)
        ):
            if model == "power" and k > 1 and (free_weights or priors.fits_gains):
                continue
            state = random_state(kernel, rng, k, on_plane)
            if free_weights:
                state = dataclasses.replace(state, log_gains=np.zeros(k), log_scale=0.0)
            for white, each_room in itertools.product(
                (
                    Whitening.identity(model, kernel.n_leds),
                    whitening_reference(model, kernel, state, float(k)),
                ),
                (room, levelled),
            ):
                values = np.asarray(rng.standard_normal(white.weights.shape[0]))
                objective = Objective(kernel, white, values, free_weights, priors)
                examples.append((each_room, objective, state))
    return examples


def sandwich_parts(answer: Any) -> tuple[Any, ...]:
    """The covariances and the fit quality's numbers (its verdict as its index)."""
    covariances, fit = answer
    verdict = ("ok", "poor", "scale_mismatch").index(fit.quality)
    return (covariances, fit.chi2_per_dof, fit.scale, fit.dof, verdict)


def _search_run(room: PreparedRoom, rng: np.random.Generator) -> Run:
    """A search's run in ``room``: the plain model of two random targets plus noise."""
    truth = random_state(room.kernel, rng, 2)
    identity = room.identity
    clean = Objective(room.kernel, identity, np.zeros(identity.weights.shape[0]), False)
    modelled = -residual_reference(clean, clean.pack(truth), truth)
    values = modelled + 1e-3 * rng.standard_normal(modelled.shape[0])
    return Run(values=values, priors=room.growth_priors)


def grow_examples() -> list[Arguments]:
    """``(room, run, state, inner_iter, avoid, n_targets)`` of the paper room's correlation
    search: a step from K = 0, 1 and 3 targets, only inserted or refined too, with points to
    avoid or none; and the steps from none to 1 and to 3 targets."""
    room = GridlessSolver(_paper_fingerprint(), "correlation").room
    rng = np.random.default_rng(22)
    centres = room.centres
    examples: list[Arguments] = []
    for k, inner_iter, avoiding in itertools.product((0, 1, 3), (0, 2), (False, True)):
        state = random_state(room.kernel, rng, k) if k else FitState.empty()
        avoid = centres[rng.choice(len(centres), 2)] if avoiding else None
        examples.append((room, _search_run(room, rng), state, inner_iter, avoid, None))
    for n_targets in (1, 3):
        avoid = centres[rng.choice(len(centres), 2)]
        examples.append((room, _search_run(room, rng), FitState.empty(), 2, avoid, n_targets))
    return examples


def refine_examples() -> list[Arguments]:
    """``(room, run, state, max_iter, rounds)`` of the paper room's correlation search: K = 1
    to 3 targets near the run's, one round and up to three, whitened and in the plain
    metric."""
    rng = np.random.default_rng(23)
    examples: list[Arguments] = []
    for whiten in (True, False):
        options = dataclasses.replace(GridlessOptions(), whiten=whiten)
        room = GridlessSolver(_paper_fingerprint(), "correlation", options).room
        for k, rounds in itertools.product((1, 2, 3), (1, 3)):
            state = random_state(room.kernel, rng, k)
            examples.append((room, _search_run(room, rng), state, 50, rounds))
    return examples


def escape_test_examples() -> list[Arguments]:
    """``(room, run, state)`` of the paper room's correlation search: K = 1 to 3 targets at
    random, and at the run's own two targets (a fit that leaves only its noise, so that the
    grid is scored; under the count's threshold and under one that any point passes),
    whitened and in the plain metric."""
    rng = np.random.default_rng(25)
    examples: list[Arguments] = []
    for whiten, threshold in ((True, None), (True, -1.0), (False, None)):
        options = dataclasses.replace(GridlessOptions(), whiten=whiten)
        if threshold is not None:
            options = dataclasses.replace(options, count_threshold=threshold)
        room = GridlessSolver(_paper_fingerprint(), "correlation", options).room
        for k in (1, 2, 3):
            examples.append((room, _search_run(room, rng), random_state(room.kernel, rng, k)))
        for noise in (1e-6, 1e-3):
            truth = dataclasses.replace(
                random_state(room.kernel, rng, 2), weights=np.ones(2), log_gains=np.zeros(2)
            )
            truth.noise = 0.05
            identity = room.identity
            clean = Objective(room.kernel, identity, np.zeros(identity.weights.shape[0]), False)
            modelled = -residual_reference(clean, clean.pack(truth), truth)
            values = modelled + noise * rng.standard_normal(modelled.shape[0])
            examples.append((room, Run(values=values, priors=room.growth_priors), truth))
    return examples


def search_parts(answer: FitState) -> tuple[Any, ...]:
    """A search step's state: every value, and whether its last fit converged."""
    return (
        answer.positions,
        answer.noise,
        answer.weights,
        answer.heights,
        answer.log_gains,
        answer.log_scale,
        answer.converged,
    )


def covariance_radii_examples() -> list[Arguments]:
    """Error ellipses of axes' ratios from a circle's 1 to 10^-6, turned at random, one to
    eleven per call, at the 95 % level and the 68 % one; with a diagonal one, a zero one and
    a singular one (the non-finite ones: tests/vlp/test_uncertainty.py)."""
    rng = np.random.default_rng(17)
    examples = []
    for level, n in ((0.95, 1), (0.95, 4), (0.95, 11), (0.68, 5)):
        one_d = float(special.ndtri(0.5 + 0.5 * level))  # the root as the ratio -> 0
        two_d = math.sqrt(-2.0 * math.log1p(-level))  # and at 1 (Rayleigh)
        ratios = np.sqrt(10.0 ** rng.uniform(-12.0, 0.0, n))
        ratios[0] = 1.0
        angles = rng.uniform(0.0, math.pi, n)
        majors = 10.0 ** rng.uniform(-6.0, 0.0, n)  # m^2
        turns = np.stack(
            (
                np.column_stack((np.cos(angles), -np.sin(angles))),
                np.column_stack((np.sin(angles), np.cos(angles))),
            ),
            axis=1,
        )
        axes = np.zeros((n, 2, 2))
        axes[:, 0, 0], axes[:, 1, 1] = majors, majors * ratios**2
        covariances = turns @ axes @ turns.transpose(0, 2, 1)
        if n > 4:
            covariances[1] = np.diag([3e-4, 1e-4])
            covariances[2] = 0.0
            covariances[3] = [[1e-4, 1e-4], [1e-4, 1e-4]]
        examples.append((covariances, level, one_d, two_d))
    return examples


def profile_cells_examples() -> list[Arguments]:
    """The paper room's grid; 1 and 4 terminals' amplitudes of cells (0.8-1.2x per LED), one
    weight each or one per LED, their optima at their truths, at random cells, or off the
    floor (nothing around them); the gain's prior or none."""
    room = GridlessSolver(_paper_fingerprint(), "correlation").room
    gains, centres, (n_leds, n_cells) = room.gains, room.centres, room.gains.shape
    rng = np.random.default_rng(24)
    examples: list[Arguments] = []
    for k, per_led, where, log_gain_sd in itertools.product(
        (1, 4), (False, True), ("truth", "random", "off"), (0.1, None)
    ):
        truths = rng.choice(n_cells, k)
        values = gains[:, truths].T * rng.uniform(0.8, 1.2, (k, n_leds))
        spread = rng.uniform(0.5, 2.0, (k, n_leds if per_led else 1))
        weights = np.broadcast_to(spread / (1e-3 * values.max()), (k, n_leds)).copy()
        cells = truths if where == "truth" else rng.choice(n_cells, k)
        previous = centres[cells] if where != "off" else np.full((k, 2), -5.0)
        examples.append((values, weights, gains, gains**2, centres, previous, log_gain_sd))
    return examples
