"""The nuisance stages of the default solver, each a function of the run and its state that
returns the state it keeps, with its own test and gate (docs/explanation/solver.md,
"Nuisance stages", "Room tolerances"): the common scale and heights, then the gains
(:func:`with_nuisances`); then the LEDs' tolerances in a joint fit
(:func:`with_room_tolerances`).
"""

from __future__ import annotations

import math

import numpy as np

from ...typing import FloatArray
from .fitting import (
    Run,
    run_objective,
    whitening_of,
)
from .joint_model import RoomTolerances
from .model import (
    _Slots,
    gram,
)
from .room import MAX_MISFIT_ENTRIES, PreparedRoom
from .search import polish
from .state import FitState
from .tolerances import (
    GridMoves,
    ToleranceFit,
    fit_room_tolerances,
)


def with_nuisances(room: PreparedRoom, run: Run, fixed: FitState) -> FitState:
    """Free the common scale and the heights, then the targets' gains; keep each stage
    only when it explains the data significantly better than the one before
    (docs/explanation/solver.md, "Nuisance stages").

    Each free parameter lowers the whitened cost by about one unit of noise even when
    the targets are exactly as modelled, and costs accuracy (K = 8, paper room: free
    gains fit the noise); so a freer fit must beat the one before by more than its extra
    parameters' chi-square would by chance (mean plus three standard deviations). A score
    test comes first (one evaluation: the decrease the Gauss-Newton step of the freer
    model promises at the current fit); only a promising stage is fitted.
    """
    best, kept = fixed, run.priors
    k = fixed.n_targets
    free_weights = room.options.free_weights
    white = whitening_of(room, best)
    # The freest stage is tested first: when even it promises nothing, neither does any
    # stage in between (one evaluation in the common case of a room as modelled).
    for index, priors in enumerate([room.stages[-1], *room.stages] if room.stages else []):
        run.priors = priors
        slots = _Slots.make(k, priors, free_weights)
        extra = slots.size - _Slots.make(k, kept, free_weights).size
        significant = extra + room.options.stage_significance * math.sqrt(2.0 * extra)
        objective = run_objective(room, run, white)
        theta = objective.pack(best)
        normal, gradient, before = gram(objective, theta, best)
        try:
            promised = float(gradient @ np.linalg.solve(normal, gradient))
        except np.linalg.LinAlgError:
            promised = float(gradient @ np.linalg.lstsq(normal, gradient, rcond=None)[0])
        if promised <= significant:
            if index == 0:
                break
            continue
        if index == 0 and len(room.stages) > 1:
            continue  # promising: now stage by stage, the cheapest first
        freed = polish(room, run, best)
        if before - objective.cost(freed)[0] > significant:
            best, kept = freed, priors
            white = whitening_of(room, best)
    run.priors = kept
    return best


def with_room_tolerances(
    room: PreparedRoom, run: Run, state: FitState, others: tuple[FloatArray, ...] = ()
) -> ToleranceFit | None:
    """The fit with the room's tolerances (LED amplitudes and beams, optionally the
    photodiodes' tilts) as nuisance parameters (:mod:`.gridless.tolerances`; see
    docs/explanation/solver.md, "Room tolerances"); None where
    it is not tried or not kept.

    Tried only when the fit shows a misfit (whitened cost per degree of freedom above
    ``tolerance_misfit_ratio``), then gated by :func:`.gridless.tolerances.fit_room_tolerances`
    (a score test, and a decrease beyond ``tolerance_significance`` standard deviations
    of chance, 3 as the other stages). Fitted always, the tolerances fit the noise of a
    room exactly as modelled and cost it accuracy; the gate was chosen on three rooms and
    seven conditions (docs/decisions/room-tolerance-stage.md). The
    joint fit then tries long moves of each target and the placements ``others`` (the
    restarts' optima not picked), kept when they lower its cost (``tolerance_jumps``),
    and last each photodiode's tilt (:func:`tolerance_tilt_sd`).

    Correlation model, K >= 2 (one target's LED errors cannot be told from its
    position), fixed unit weights, rooms whose Jacobian stays small (dense rooms) and
    Lambertian LEDs: the stage's beam tolerance is a change of the Lambertian order, which
    a tabulated beam (a photometric table, or one a survey measured) does not have.
    """
    opts = room.options
    k = state.n_targets
    n_leds = room.fingerprint.n_leds
    gain_sd, scale_sd = opts.log_gain_sd, opts.log_scale_sd
    if (
        room.model != "correlation"
        or opts.led_log_amplitude_sd is None
        or gain_sd is None
        or scale_sd is None
        or opts.free_weights
        or room.kernel.has_beams
        or k < 2
        or not room.dense
        or run.values.shape[0] * (5 * k + 2 * n_leds + 2) > MAX_MISFIT_ENTRIES
    ):
        return None
    white = whitening_of(room, state)
    data_cost = run_objective(room, run, white).data_cost(state)[0]
    dof = white.weights.shape[0] - 3 * k - 2
    if dof <= 0 or data_cost <= opts.tolerance_misfit_ratio * dof:
        return None  # the fit leaves only noise: nothing for the tolerances to explain
    tolerances = RoomTolerances(
        opts.led_log_amplitude_sd, opts.led_half_power_sd_deg, opts.room_tilt_sd
    )
    return fit_room_tolerances(
        room.kernel,
        run.values,
        state,
        (gain_sd, scale_sd),
        tolerances,
        opts.tolerance_significance,
        GridMoves(
            room.gains,
            room.centres,
            room.avoid_radius,
            room.priors.height_mean,
            others,
            0.5 * room.fingerprint.layout.grid.step,
        )
        if opts.tolerance_jumps
        else None,
        opts.tolerance_score_ratio,
        tolerance_tilt_sd(room),
    )


def tolerance_tilt_sd(
    room: PreparedRoom,
) -> float:
    """The prior sd (per tangent component, about radians) of the photodiodes' tilts in
    the joint fit's last stage: the layout's spread, else the hand-held default
    (``tolerance_tilt_sd``); 0 where the layout's photodiodes are level or the stage is
    off."""
    opts = room.options
    if opts.tolerance_tilt_sd <= 0 or room.receivers_level:
        return 0.0
    declared = math.radians(room.fingerprint.layout.grid.receiver_tilt_sd)
    return declared if declared > 0 else opts.tolerance_tilt_sd
