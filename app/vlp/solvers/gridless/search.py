"""The nominal search of the default solver (docs/explanation/solver.md, "Search",
"Escapes", "Counting", "Prescale"): ADCG insertions and refinements (one compiled call each
where :func:`search_compiles` says so), the escapes from local minima (relocation, restarts,
far relocation of ambiguous estimates), counting by energy and by the rank of ``R``, and the
guessed common scale.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ..._kernels import dispatch
from ...ambiguity import reaching_beyond
from ...measurements import Measurement, noise_atom, summed_terminals
from ...typing import FloatArray, IntArray
from ._compiled import search as compiled_search
from .fitting import (
    Run,
    atom_energy,
    fits_to_noise,
    grid_correlations,
    insertion_scores,
    leaves_noise,
    lm_fit,
    noise_test,
    plain_cost,
    residual_of,
    run_objective,
    whitening_of,
)
from .lm import STEP_TOL_M
from .report import profiles
from .room import PreparedRoom
from .state import (
    MAX_LOG_SCALE,
    PLAIN_FACTS,
    FitState,
)
from .whitening import Whitening
from .whitening_memo import state_key

# A count read off the rank of R replaces a smaller count by energy only when its fit's
# variance ratio against that one is above this (gridless.search.explains_more).
_COUNT_F_RATIO = 10.0
# No points to avoid (the compiled growth step takes an (n, 2) array).
_NO_POINTS = np.zeros((0, 2))


def search_state(state: FitState) -> tuple[Any, ...]:
    """A search state as the compiled search steps take it: ``(positions, noise, heights,
    weights, log_gains, log_scale)``."""
    return (
        np.ascontiguousarray(state.positions, dtype=np.float64),
        float(state.noise),
        np.ascontiguousarray(state.heights, dtype=np.float64),
        np.ascontiguousarray(state.weights, dtype=np.float64),
        np.ascontiguousarray(state.log_gains, dtype=np.float64),
        float(state.log_scale),
    )


class Search(NamedTuple):
    """One nominal search (gridless.search.nominal_search): its run, its fit, the restarts' optima
    it did not pick and the common scale it ran at."""

    run: Run
    state: FitState
    others: list[FloatArray]
    prescale: float


def insert_target(
    room: PreparedRoom,
    run: Run,
    state: FitState,
    white: Whitening,
    avoid: FloatArray | None = None,
    scores: FloatArray | None = None,
) -> FitState:
    """Add a unit-weight target at the grid point that most lowers the cost (not within
    ``_avoid_radius`` of the points ``avoid``, shape (n, 2), when given). ``scores``: the
    state's :func:`scores_of` in ``white``'s metric, when the caller has them."""
    if scores is None:
        metric = scoring_metric(room, white)
        residual = residual_of(room, run, metric, state)
        if room.power_scan is not None and (avoid is None or avoid.shape[0] == 0):
            found = room.power_scan.best(
                residual, math.exp(state.log_scale), float(metric.weights[0]) ** 2
            )
            if found is not None:
                return state.with_target(room.centres[found[0]], room.priors.height_mean)
        scores = insertion_scores(room, metric, residual, math.exp(state.log_scale))
    if avoid is not None and avoid.shape[0] > 0:
        allowed = scores.copy()
        for point in avoid:
            near = np.sum((room.centres - point) ** 2, axis=1) < room.avoid_radius**2
            allowed[near] = -np.inf
        if np.isfinite(allowed).any():
            scores = allowed
    best = int(np.argmax(scores))
    return state.with_target(room.centres[best], room.priors.height_mean)


def scoring_metric(room: PreparedRoom, white: Whitening) -> Whitening:
    """The metric insertions score in: ``white``, or the plain one in large rooms, where
    whitened atom norms would need the rotated gains of every grid point."""
    return white if room.dense else room.identity


def scores_of(room: PreparedRoom, run: Run, state: FitState, white: Whitening) -> FloatArray:
    """:func:`insertion_scores` of every grid point for one more target in ``state``."""
    metric = scoring_metric(room, white)
    residual = residual_of(room, run, metric, state)
    return insertion_scores(room, metric, residual, math.exp(state.log_scale))


def grow(
    room: PreparedRoom,
    run: Run,
    state: FitState,
    inner_iter: int,
    avoid: FloatArray | None = None,
    n_targets: int | None = None,
) -> FitState:
    """One ADCG step: insert at the best grid point, then refine everything (briefly,
    in the metric of the state before the insertion), with ``grow_without_noise`` the
    noise coefficient held at 0; with ``n_targets``, the steps up to that many targets (the
    first one away from ``avoid``)."""
    return dispatch(grow_kernel, grow_reference)(room, run, state, inner_iter, avoid, n_targets)


def search_compiles(room: PreparedRoom, run: Run) -> bool:
    """Whether :func:`grow_kernel` and :func:`refine_kernel` run as one compiled call each
    (:mod:`.gridless._compiled.search`): the correlation model in a dense room, searching
    (positions and noise only), fixed weights."""
    return room.search_constants is not None and run.priors is room.growth_priors


def grow_kernel(
    room: PreparedRoom,
    run: Run,
    state: FitState,
    inner_iter: int,
    avoid: FloatArray | None,
    n_targets: int | None = None,
) -> FitState:
    """:func:`grow_reference` in one compiled call where :func:`search_compiles` (the same
    kernels, in the same order: the same state to the bit). The states' whitenings are
    computed there, not kept: a growth step's state is never whitened again (the next step
    adds a target), but for the last state of a count, which the polish whitens once
    more."""
    if not search_compiles(room, run):
        return grow_reference(room, run, state, inner_iter, avoid, n_targets)
    k = state.n_targets
    ceiling = 0.0 if room.grow_without_noise else math.inf
    problem = (
        *search_problem(room, run),
        search_state(state),
        room.gains,
        room.centres,
        _NO_POINTS if avoid is None else np.ascontiguousarray(avoid, dtype=np.float64),
        room.avoid_radius,
    )
    # One step, or the steps up to n_targets: the bounds say how many targets to reach.
    target_count = k + 1 if n_targets is None else n_targets
    positions, noise, total, used = compiled_search.grow_kernel(
        *problem, *room.search_objective(ceiling).bounds(target_count), inner_iter
    )
    added = positions.shape[0] - k
    weights, heights = np.ones(added), np.full(added, room.priors.height_mean)
    log_gains = np.zeros(added)
    if k > 0:
        weights = np.concatenate((state.weights, weights))
        heights = np.concatenate((state.heights, heights))
        log_gains = np.concatenate((state.log_gains, log_gains))
    grown = FitState(positions, weights, float(noise), heights, log_gains, state.log_scale)
    on_plane = room.priors.height_mean == room.kernel.receiver_height
    if k == 0:
        grown.facts = (on_plane, state.log_scale == 0.0)
    elif on_plane and state.facts == PLAIN_FACTS:
        grown.facts = state.facts  # unit-gain targets on the plane added to a plain state
    if inner_iter > 0:
        run.iterations += int(total)
        grown.converged = used < inner_iter
    return grown


def grow_reference(
    room: PreparedRoom,
    run: Run,
    state: FitState,
    inner_iter: int,
    avoid: FloatArray | None,
    n_targets: int | None = None,
) -> FitState:
    """:func:`grow` step by step in Python."""
    if n_targets is not None:
        while state.n_targets < n_targets:
            first = state.n_targets == 0
            state = grow_reference(room, run, state, inner_iter, avoid if first else None)
        return state
    white = whitening_of(room, state)
    grown = insert_target(room, run, state, white, avoid)
    if inner_iter > 0:
        # Gains, scale and heights stay put while targets are being inserted: free, the
        # first targets would take the energy of those not yet inserted.
        grown, _ = lm_fit(
            room,
            run,
            white,
            grown,
            inner_iter,
            nuisance=False,
            around=grown.positions[-1:],
            ceiling=0.0 if room.grow_without_noise else math.inf,
        )
    return grown


def refine(room: PreparedRoom, run: Run, state: FitState, max_iter: int, rounds: int) -> FitState:
    """LM rounds, each whitened by the covariance plugged in from the previous one."""
    return dispatch(refine_kernel, refine_reference)(room, run, state, max_iter, rounds)


def refine_kernel(
    room: PreparedRoom, run: Run, state: FitState, max_iter: int, rounds: int
) -> FitState:
    """:func:`refine_reference` in one compiled call where :func:`search_compiles` and
    there are targets (the same kernels, in the same order: the same state to the bit;
    the rounds' whitenings are not kept, no later step asks for them)."""
    if state.n_targets == 0 or not search_compiles(room, run):
        return refine_reference(room, run, state, max_iter, rounds)
    lower, upper = room.search_objective(math.inf).bounds(state.n_targets)
    positions, noise, total, last = compiled_search.refine_kernel(
        *search_problem(room, run), search_state(state), lower, upper, rounds, max_iter
    )
    run.iterations += int(total)
    refined = FitState(
        positions,
        state.weights,
        float(noise),
        state.heights,
        state.log_gains,
        state.log_scale,
        facts=state.facts,
    )
    refined.converged = last < max_iter
    return refined


def refine_reference(
    room: PreparedRoom, run: Run, state: FitState, max_iter: int, rounds: int
) -> FitState:
    """:func:`refine` round by round in Python."""
    for round_index in range(max(rounds, 1)):
        before = run.iterations
        state, _ = lm_fit(room, run, whitening_of(room, state), state, max_iter)
        if round_index > 0 and run.iterations - before <= 2:
            break  # the re-whitened metric no longer moves the fit
    return state


def search_problem(room: PreparedRoom, run: Run) -> tuple[Any, ...]:
    """The compiled search steps' ``(channel, table, search)`` for ``run``
    (:func:`.gridless._compiled.search.grow_kernel`)."""
    assert room.search_constants is not None
    channel, table, layout, priors, is_diag = room.search_constants
    search = (
        room.identity.compiled(),
        room.options.whiten,
        is_diag,
        run.values,
        room.kernel.receiver_height,
        layout,
        priors,
        room.lm.initial_damping,
        room.lm.tol,
        STEP_TOL_M,
    )
    return channel, table, search


def needs_escape(room: PreparedRoom, run: Run, state: FitState) -> bool:
    """True when the fit looks like a local minimum worth relocating or restarting from
    (docs/explanation/solver.md, "Escapes").

    Two signs, either suffices: (1) the whitened cost per degree of freedom is above
    ``misfit_ratio``: a complete fit leaves only noise, about one unit per degree of
    freedom in the whitened metric; (2) one more unit-weight target would still lower
    the cost by at least ``count_threshold`` of its own energy somewhere: a target the
    fit has not found (two estimates sharing one terminal, another left out). The
    threshold separates good fits from gross failures (bench/tune_gridless.py,
    docs/decisions/gridless-defaults.md).

    With far relocation (the power model's default) always, from K = 2: the power
    model's noise atom (ones) is nearly a signal direction, so a fit stuck far from the
    truth raises its fitted noise level instead of its whitened cost, and neither sign
    shows (docs/decisions/power-model-search.md).
    """
    if room.relocate_far and state.n_targets >= 2:
        return True
    return dispatch(escape_test_kernel, escape_test_reference)(room, run, state)


def escape_test_kernel(room: PreparedRoom, run: Run, state: FitState) -> bool:
    """:func:`escape_test_reference` with the state's plug-in whitening, its whitened
    residual and the grid's inner products in one compiled call, where
    :func:`search_compiles` and they are not known yet (the same kernels in the same
    order: the same numbers). The whitening, its data and the residual are kept where
    the reference keeps them (:func:`.fitting.whitened_residual`), for the stages after."""
    key = (state_key(state), run.priors)
    if (
        state.n_targets == 0
        or not room.options.whiten
        or not search_compiles(room, run)
        or key in run.whitened
    ):
        return escape_test_reference(room, run, state)
    rotation, weights, data, residual, num, norms = compiled_search.escape_test_kernel(
        *search_problem(room, run), search_state(state), room.gains
    )
    n_leds = room.fingerprint.n_leds
    white = room.whitenings.get(state, lambda _: Whitening(room.model, n_leds, rotation, weights))
    white.keep(run.values, data)
    run.whitened[key] = (white, residual)
    if not leaves_noise(room, state, residual):
        return True
    return misses_a_target(room, state, num, norms)


def escape_test_reference(room: PreparedRoom, run: Run, state: FitState) -> bool:
    """:func:`needs_escape`'s two signs, each piece by the kernels in use."""
    white, residual, within = noise_test(room, run, state)
    # With no degree of freedom left (power model, 2K + 1 >= M) no cost tells a local
    # minimum from the truth: always escaping doubles the time there but is worth about
    # 8 % of the error (docs/explanation/uncertainty.md#the-fits-quality).
    if not within:
        return True
    if not room.dense:
        white = room.identity
        residual = residual_of(room, run, white, state)
    weight = math.exp(state.log_scale)
    if room.power_scan is not None:
        found = room.power_scan.best(residual, weight, float(white.weights[0]) ** 2)
        if found is not None:
            _, gain_best, norm_best = found
            return bool(gain_best > room.options.count_threshold * weight**2 * norm_best)
    return misses_a_target(room, state, *grid_correlations(room, white, residual))


def misses_a_target(
    room: PreparedRoom, state: FitState, num: FloatArray, norms_sq: FloatArray
) -> bool:
    """Whether one more unit-weight target would lower the cost by at least
    ``count_threshold`` of its own energy at the best grid point, from the grid's
    ``<c psi_j, r>`` and ``||c psi_j||^2`` (:func:`.fitting.grid_correlations`)."""
    weight = math.exp(state.log_scale)
    gain = 2.0 * weight * num - weight**2 * norms_sq
    best = int(np.argmax(gain))
    return bool(gain[best] > room.options.count_threshold * weight**2 * norms_sq[best])


def count_and_fit(room: PreparedRoom, run: Run) -> FitState:
    """Grow one target at a time while each brings its own energy (unknown K;
    docs/explanation/solver.md, "Counting").

    A real target removes about its own atom energy ``||phi(p)||^2`` from the plain
    residual; a spurious one, of unit weight, adds about as much. A state with more
    targets is kept when its cost is below the best so far by ``count_threshold`` times
    the energy of the targets it adds; up to ``count_lookahead`` more are tried before
    stopping (a close pair is often only resolved one target later).
    """
    opts = room.options
    state = FitState.empty()
    best, best_cost = state, plain_cost(room, run, state)
    while state.n_targets < room.max_count:
        state = grow(room, run, state, opts.count_inner_iter)
        state_cost = plain_cost(room, run, state)
        extra = state.n_targets - best.n_targets
        weights = state.effective_weights()[-extra:]
        energy = sum(
            atom_energy(room, p, float(w))
            for p, w in zip(state.positions[-extra:], weights, strict=True)
        )
        if best_cost - state_cost >= opts.count_threshold * energy:
            best, best_cost = state, state_cost
        elif extra > opts.count_lookahead:
            break
    if best.n_targets == 0:
        # Nothing brings its own energy (noise only): still answer one best guess.
        best = grow(room, run, best, opts.count_inner_iter)
    return best


def relocate(
    room: PreparedRoom,
    run: Run,
    state: FitState,
    far: bool | None = None,
    targets: IntArray | None = None,
) -> tuple[FitState, bool]:
    """ADCG's non-convex escape: move one target at a time to the best grid point of the
    residual left by the others, keep the move when the refined cost is lower.

    That point is usually the target's own spot. With ``far`` (default
    ``relocate_far``) such a target is tried at the best point of that residual at least
    the restarts' radius from its spot; with ``relocate_to_missing`` or ``far`` then at
    the best point of the whole residual (where a target is missing): the escapes from
    two estimates sharing one target while another has none. The first move that lowers
    the cost is kept. ``targets``: only these are moved (default all).
    """
    far = room.relocate_far if far is None else far
    moved = False
    step = room.fingerprint.layout.grid.step
    n_targets = state.n_targets
    white = whitening_of(room, state)
    cost = run_objective(room, run, white).cost(state)[0]
    missing: FloatArray | None = None
    for k in range(n_targets) if targets is None else targets:
        keep = np.arange(n_targets) != k
        others = state.subset(keep)
        own = state.positions[k]
        # The far try scores the same residual: computed once for both.
        scores = None if room.power_scan is not None else scores_of(room, run, others, white)
        candidate = insert_target(room, run, others, white, scores=scores)
        tries = [candidate]
        if np.linalg.norm(candidate.positions[-1] - own) <= 1.5 * step:
            tries = []
            if far:
                tries.append(
                    insert_target(room, run, others, white, avoid=own[np.newaxis], scores=scores)
                )
            if room.relocate_to_missing or far:
                if missing is None:
                    missing = insert_target(room, run, state, white).positions[-1]
                if all(
                    np.linalg.norm(missing - point) > 1.5 * step
                    for point in [own, *(tried.positions[-1] for tried in tries)]
                ):
                    tries.append(others.with_target(missing, room.priors.height_mean))
        for candidate in tries:
            # The moved target's old and new neighbourhoods (large rooms; all targets
            # else).
            changed = np.vstack((candidate.positions[-1:], state.positions[k : k + 1]))
            candidate, candidate_cost = lm_fit(
                room, run, white, candidate, room.options.final_iter, around=changed
            )
            if candidate_cost < cost:
                # Keep the original order: the moved target takes slot k.
                order = np.insert(np.arange(n_targets - 1), k, n_targets - 1)
                state = candidate.reordered(order)
                cost, moved = candidate_cost, True
                missing = None
                break
    return state, moved


def polish(room: PreparedRoom, run: Run, state: FitState) -> FitState:
    """Whitened refinement rounds, then relocation passes while the fit looks stuck,
    then (``relocate_ambiguous``) far relocation of the estimates that fit as well far
    away."""
    opts = room.options
    state = refine(room, run, state, opts.final_iter, opts.whiten_rounds)
    for _ in range(opts.relocate_passes):
        if not needs_escape(room, run, state):
            break
        state, moved = relocate(room, run, state)
        if not moved:
            break
        state = refine(room, run, state, opts.final_iter, 1)
    if room.relocate_ambiguous and state.n_targets >= 2 and fits_to_noise(room, run, state):
        explained, best = profiles(room, run, state)
        ambiguous = reaching_beyond(
            explained, best, room.centres, state.positions, room.avoid_radius
        )
        if ambiguous.size:
            state, moved = relocate(room, run, state, far=True, targets=ambiguous)
            if moved:
                state = refine(room, run, state, opts.final_iter, 1)
    return state


def fit_known(room: PreparedRoom, run: Run, n_targets: int, avoid: FloatArray) -> FitState:
    """Greedy growth to ``n_targets`` (first insertion away from ``avoid``), polished."""
    state = FitState.empty()
    if n_targets > 0:
        state = grow(room, run, state, room.lm.inner_iter, avoid, n_targets)
    return polish(room, run, state)


def guessed_prescale(room: PreparedRoom, values: FloatArray, n_targets: int | None) -> float:
    """A first guess of the common power scale, when K is known and the received power
    per target is more than 1.5x outside what any grid point gives (brightest to
    faintest): the power per target over the room's mean. Else 1, and the search runs
    exactly as in a room measured as modelled (docs/explanation/solver.md, "Prescale")."""
    if n_targets is None:
        return 1.0
    per_target = float(values[room.diagonal].sum()) / n_targets
    low, high = room.energy_band
    if not math.isfinite(per_target) or low / 1.5 <= per_target <= 1.5 * high:
        return 1.0
    ratio = max(per_target, 1e-300) / room.mean_column_energy
    return float(np.clip(ratio, math.exp(-MAX_LOG_SCALE), math.exp(MAX_LOG_SCALE)))


def nominal_search(
    room: PreparedRoom, values: FloatArray, n_targets: int | None, prescale: float | None = None
) -> Search:
    """The nominal fit of ``values`` (normalised units) with K counted or given, run at
    the common scale ``prescale`` (else guessed by :func:`guessed_prescale`)."""
    if prescale is None:
        prescale = guessed_prescale(room, values, n_targets)
    # The whole search runs on the measurement divided by the guessed scale.
    run = Run(values=values / prescale, priors=room.growth_priors)
    # Local optima the search found but did not pick: the joint fit with the room's
    # tolerances, which can tell them apart better, tries them again.
    others: list[FloatArray] = []
    if n_targets is None:
        return Search(run, polish(room, run, count_and_fit(room, run)), others, prescale)
    state = fit_known(room, run, n_targets, np.zeros((0, 2)))
    if n_targets < 2 or room.restarts == 0:
        return Search(run, state, others, prescale)  # no restarts: no cost to compare
    cost = plain_cost(room, run, state)
    firsts = [state.positions[0]]
    for _ in range(room.restarts):
        if not needs_escape(room, run, state):
            break
        other = fit_known(room, run, n_targets, np.array(firsts))
        firsts.append(other.positions[0])
        other_cost = plain_cost(room, run, other)
        if other_cost < cost:
            state, cost, other = other, other_cost, state
        others.append(other.positions)
    return Search(run, state, others, prescale)


def scale_free_fit(room: PreparedRoom, values: FloatArray, search: Search) -> tuple[float, float]:
    """The plain cost of a search's fit of ``values`` with its targets' atoms under
    their least-squares common scale (the noise term as fitted), and that scale: what
    the fit leaves whatever the measurement's scale, so fits run at different guessed
    scales compare."""
    run, state = search.run, search.state
    atom = room.identity.data(noise_atom(room.model, room.fingerprint.n_leds))
    noise = state.noise * atom
    signal = run.values - residual_of(room, run, room.identity, state) - noise
    data = values - search.prescale * noise
    energy = float(signal @ signal)
    scale = float(data @ signal) / energy if energy > 0.0 else 0.0
    rest = data - scale * signal
    return float(rest @ rest), scale


def search_at_scale(room: PreparedRoom, values: FloatArray, n_targets: int) -> tuple[Search, float]:
    """:func:`nominal_search` with K given (read off the rank) and its fit's cost at its
    least-squares scale (:func:`scale_free_fit`). When that scale is more than
    ``rescale_search`` off the one the search ran at, searched again at it, and the fit
    that leaves less is kept. Unit-weight atoms under a scale error of 10-20 % misplace
    targets (the insertions and the first refinements run before the scale is fitted),
    and such a fit may not show that the count by energy left targets out; the data
    show the scale once positions are roughly right. (With K given by the client it was
    measured mixed, so it is not used there: docs/decisions/count-by-rank.md
    of R".)"""
    first = nominal_search(room, values, n_targets)
    cost, scale = scale_free_fit(room, values, first)
    tolerance = room.options.rescale_search
    if tolerance is None or not (
        scale > 0.0 and abs(math.log(scale / first.prescale)) > math.log1p(tolerance)
    ):
        return first, cost
    second = nominal_search(room, values, n_targets, scale)
    second_cost, _ = scale_free_fit(room, values, second)
    return (second, second_cost) if second_cost < cost else (first, cost)


def explains_more(n_values: int, cost: float, more_cost: float, extra: int) -> bool:
    """Whether a fit with ``extra`` more targets leaves ``more_cost`` where the other
    leaves ``cost``, by far more than fitting noise with their 2 ``extra`` coordinates
    does: the variance ratio (F statistic) of the two fits above
    :data:`_COUNT_F_RATIO`. A target the smaller count left out leaves its whole signal
    in that fit's residual; spare targets on noise take out about their share of it
    (a ratio near 1), and a spare unit-weight target where nothing is adds to it
    (measured in docs/decisions/count-by-rank.md)."""
    dof = max(n_values - 2 * extra - 2, 1)
    decrease = (cost - more_cost) / (2 * extra)
    return bool(decrease > _COUNT_F_RATIO * max(more_cost, 0.0) / dof)


def counted_search(
    room: PreparedRoom, measurement: Measurement, values: FloatArray, n_targets: int | None
) -> Search:
    """The nominal fit of ``values`` (normalised units): K given, else counted by energy
    and, with ``count_by_rank``, checked against the rank of the correlation matrix
    (docs/explanation/solver.md, "Counting").

    A sum of K terminals' outer products has rank K, whatever the scale. A count above it
    is wrong; one below it is either a low scale (the energy rule counts in units of the
    fingerprint's) or terminals that saw no LED (noise only): the rank's fit is taken when
    it leaves far less, at the scale the data show.
    """
    search = nominal_search(room, values, n_targets)
    if n_targets is not None or not room.options.count_by_rank:
        return search
    counted = search.state.n_targets
    summed = summed_terminals(measurement)
    if summed is None or summed > room.max_count or summed == counted:
        return search
    known, known_cost = search_at_scale(room, values, summed)
    if summed < counted or explains_more(
        values.shape[0], scale_free_fit(room, values, search)[0], known_cost, summed - counted
    ):
        return known
    return search
