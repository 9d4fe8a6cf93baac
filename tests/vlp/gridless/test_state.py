"""A fit state's facts (all targets on the receivers' plane, unit multipliers) where a new
state carries them from the one it was made from instead of computing them afresh
(``gridless.state``, ``gridless.model.Objective.unpack``, ``gridless.search``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.vlp.fingerprints import Fingerprint
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.solvers.gridless.fitting import Run, run_objective
from app.vlp.solvers.gridless.model import Objective
from app.vlp.solvers.gridless.search import grow_kernel, refine_kernel
from app.vlp.solvers.gridless.state import FitState, Priors


def _computed(objective: Objective, state: FitState) -> tuple[bool, bool]:
    """The facts of a copy of ``state`` that carries none."""
    return objective._state_facts(dataclasses.replace(state, facts=None))


def _plain_state(height: float) -> FitState:
    return FitState(
        np.array([[1.0, 1.2], [2.5, 3.0], [0.4, 3.3]]),
        np.ones(3),
        1e-3,
        np.full(3, height),
        np.zeros(3),
    )


@pytest.fixture(scope="module")
def objective(paper_solver: GridlessSolver) -> Objective:
    room = paper_solver.room
    return Objective(room.kernel, room.identity, np.zeros(136), False, Priors())


def test_a_plain_states_children_carry_the_facts_they_would_compute(
    objective: Objective,
) -> None:
    plane = objective.kernel.receiver_height
    state = _plain_state(plane)
    assert objective._state_facts(state) == (True, True)
    children = [
        state.with_target(np.array([2.0, 2.0]), plane),
        state.subset(np.array([True, False, True])),
        state.reordered(np.array([2, 0, 1])),
        objective.unpack(objective.pack(state) + 0.01, state),
    ]
    for child in children:
        assert child.facts == (True, True)
        assert child.facts == _computed(objective, child)


def test_a_target_off_the_plane_or_a_state_not_plain_leaves_facts_to_be_computed(
    objective: Objective,
) -> None:
    plane = objective.kernel.receiver_height
    state = _plain_state(plane)
    objective._state_facts(state)
    off = state.with_target(np.array([2.0, 2.0]), plane + 0.1)
    assert off.facts is None
    assert _computed(objective, off) == (False, True)
    gained = dataclasses.replace(state, log_gains=np.array([0.0, 0.1, 0.0]), facts=None)
    assert objective._state_facts(gained) == (True, False)
    for child in (gained.with_target(np.array([2.0, 2.0]), plane), gained.subset(np.array([0, 2]))):
        assert child.facts is None
        assert _computed(objective, child) == (True, child.n_targets == 2)
    # A fit of the nuisance parameters changes them: its state computes its own facts.
    priors = Priors(log_gain_sd=0.1, height_mean=plane)
    freed = Objective(objective.kernel, objective.white, objective.data, False, priors)
    assert freed.unpack(freed.pack(state), state).facts is None


def test_the_compiled_search_steps_carry_the_facts_they_would_compute(
    paper_fingerprint: Fingerprint,
) -> None:
    solver = GridlessSolver(paper_fingerprint, "correlation")
    room = solver.room
    rng = np.random.default_rng(3)
    run = Run(values=np.abs(rng.standard_normal(136)) * 0.1, priors=room.growth_priors)
    objective = run_objective(room, run, room.identity)
    state = FitState.empty()
    for _ in range(3):
        state = grow_kernel(room, run, state, room.lm.inner_iter, None)
        assert state.facts == (True, True)
        assert state.facts == _computed(objective, state)
    refined = refine_kernel(room, run, state, room.options.final_iter, 2)
    assert refined.facts == _computed(objective, refined) == (True, True)
    # Grown at another common scale: not unit multipliers, still on the plane.
    scaled = grow_kernel(room, run, FitState.empty(math.log(2.0)), room.lm.inner_iter, None)
    assert scaled.facts == _computed(objective, scaled) == (True, False)
