"""Compile (or load from the disk cache) every kernel before the first request.

The top of the kernels' imports: it imports every kernel's caller, and nothing in
:mod:`app.vlp` imports it but :mod:`app.vlp.solvers` (which exports :func:`warm_up`). It runs
every row of the kernel table (:mod:`._kernel_table`: each kernel on the examples its parity
test compares with its reference), then :func:`exercise`, the kernels not in the table yet
(called with compiled tuples of their own, not through a reference's arguments). The calls go
through the same code as a solve, so they compile exactly the argument types a solve uses.
"""

from __future__ import annotations

import threading

import numpy as np

from .._kernels import kernel_mode
from ..presets import paper_layout
from ..uncertainty import confidence_radii
from ._kernel_table import KERNEL_TABLE
from .gridless._compiled.channel import channel_constants, channel_rows
from .gridless._compiled.search import growth_kernel, refine_kernel
from .gridless._compiled.uncertainty import uncertainty_kernel
from .gridless.channel import ChannelKernel
from .gridless.joint_model import (
    JointModel,
    RoomTolerances,
)
from .gridless.lm import STEP_TOL_M
from .gridless.model import Objective, fit_objective
from .gridless.options import LM_DEFAULTS
from .gridless.state import FitState, Priors
from .gridless.terminals import _fit_from as terminal_fit
from .gridless.tolerances import _fit_joint
from .gridless.whitening import Whitening, compiled_indices

__all__ = ["exercise", "warm_table", "warm_up"]

_lock = threading.Lock()
_warm = False


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel the default solver uses.

    Idempotent and thread-safe; a no-op with the reference kernels. Called by the service at
    start-up, so that no terminal's request waits for the compiler.
    """
    global _warm
    if kernel_mode() != "compiled":
        return
    with _lock:
        if _warm:
            return
        warm_table()
        exercise()
        _warm = True


def warm_table() -> None:
    """Every row of the kernel table: its kernel on each of its examples."""
    for row in KERNEL_TABLE:
        for args in row.examples():
            row.kernel(*args)


def exercise() -> None:
    """The kernels not in the kernel table: evaluate, whiten, fit and take the covariances
    of a two-target state of the paper's room, both models; grow it by one target and refine
    it as the correlation search does; evaluate the joint fit under the room's tolerances
    there; fit a terminal; take an answer's radii."""
    layout = paper_layout()
    kernel = ChannelKernel(layout, 1.0)
    height = layout.grid.receiver_height
    state = FitState(
        np.array([[1.0, 1.2], [2.5, 3.0]]),
        np.ones(2),
        1e-3,
        np.full(2, height),
        np.zeros(2),
    )
    priors = Priors(0.1, 0.5, 0.05, height, (height - 0.2, height + 0.2))
    for model in ("correlation", "power"):
        white = Whitening.from_state(model, kernel, state, 2.0)
        values = np.ones(white.weights.shape[0])
        objective = Objective(kernel, white, values, False, priors)
        theta = objective.pack(state)
        objective.residual(theta, state)
        fit_objective(objective, state, max_iter=1, initial_damping=1e-3, tol=1e-6)
        # an answer's covariances (gridless.uncertainty.sandwich_covariances)
        problem = objective.compiled_problem()
        assert problem is not None
        uncertainty_kernel(*problem, theta, *objective.compiled_state(state), 1.0, False)
    # the joint fit under the room's tolerances (gridless.stages.with_room_tolerances): its
    # metric evaluates the gains; its score test the residual and Jacobian; then its LM
    joint = JointModel(kernel, state.heights, (0.1, 0.5), RoomTolerances(0.05, 3.0, 0.07))
    theta = joint.pack(state)
    white = joint.whitening(theta, state.noise)
    data = white.data(np.ones(white.weights.shape[0]))
    joint.residual_and_jacobian(theta, white, data)
    _fit_joint(joint, theta, white, data, 1)
    # a terminal's own fit evaluates the channel at one point, and runs its own LM (one
    # signature for every branch: straight up, a sent normal, a fitted tilt)
    constants = channel_constants(kernel)
    assert constants is not None  # a line-of-sight kernel always has its compiled form
    point = np.array([1.0])
    channel_rows(*constants, point, point.copy(), np.array([height]), False)
    # the correlation search's growth (a step, and the steps to K targets) and whitened
    # refinement (gridless.search.grow_compiled, refine_compiled)
    identity = Whitening.identity("correlation", kernel.n_leds)
    search = Objective(
        kernel, identity, np.zeros(identity.weights.shape[0]), False, Priors(height_mean=height)
    )
    _, search_layout, search_priors = search.compiled_state(state)
    _, _, is_diag = compiled_indices("correlation", kernel.n_leds)
    problem = (
        identity.compiled(),
        True,
        is_diag,
        np.ones(identity.weights.shape[0]),
        height,
        search_layout,
        search_priors,
        LM_DEFAULTS["correlation"].initial_damping,
        LM_DEFAULTS["correlation"].tol,
        STEP_TOL_M,
    )
    fixed = (state.positions, 1e-3, state.heights, state.weights, state.log_gains, 0.0)
    k = state.n_targets
    grid = (np.ones((kernel.n_leds, 3)), np.ones((3, 2)), np.zeros((0, 2)), 0.5)
    growth_kernel(*constants, problem, fixed, *grid, *search.bounds(k + 1), 1)
    refine_kernel(*constants, problem, fixed, *search.bounds(k), 2, 1)
    empty = (np.zeros((0, 2)), 1e-3, np.zeros(0), np.zeros(0), np.zeros(0), 0.0)
    growth_kernel(*constants, problem, empty, *grid, *search.bounds(k), 1)
    terminal_fit(
        kernel, np.ones(kernel.n_leds), np.array([1.0, 1.2]), height, True, priors, 1.0, None, 0.1
    )
    # an answer's 95 % radii (app.vlp.uncertainty.confidence_radii)
    confidence_radii(np.array([[[0.01, 0.002], [0.002, 0.004]]]))
