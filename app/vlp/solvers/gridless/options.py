"""Options of the ``gridless`` solver and its per-model Levenberg-Marquardt settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

from ...fingerprints import Fingerprint
from ...layout import Layout
from ...measurements import Model
from .channel import DiffuseTable
from .state import Priors

__all__ = [
    "LM_DEFAULTS",
    "GridlessOptions",
    "LevenbergMarquardtSettings",
    "diffuse_table",
    "nuisance_priors",
    "pick",
]

# Heights are fitted within this many prior standard deviations of the receivers' plane.
_HEIGHT_SPAN_SD = 4.0
# ... and stay this far below the lowest LED (the channel is singular at an LED).
_HEIGHT_CLEARANCE_M = 0.05

_Number = TypeVar("_Number", int, float)


@dataclass(frozen=True)
class GridlessOptions:
    """Tuning knobs and the nuisance parameters' priors (see the solver's Notes)."""

    free_weights: bool = False
    whiten: bool = True
    # None: the model's own default (see LM_DEFAULTS).
    inner_iter: int | None = None
    initial_damping: float | None = None
    lm_tol: float | None = None
    count_inner_iter: int = 4
    final_iter: int = 50
    whiten_rounds: int = 3
    # K read off the rank of R: a search whose fit shows a common scale more than this far
    # (relative) from the one it ran at is repeated at that scale
    # (gridless.search.search_at_scale; None: never).
    rescale_search: float | None = 0.05
    # K unknown: read it off the correlation matrix's rank where its spectrum says
    # (app.vlp.measurements.summed_terminals), else count by energy (count_threshold).
    count_by_rank: bool = True
    count_threshold: float = 0.2
    count_lookahead: int = 2
    relocate_passes: int = 1
    # Relocation also tries moving a target whose own spot is still its best point to the
    # best point of the whole residual (where a target is missing). None: in rooms too large
    # for the dense dictionary, where greedy growth leaves targets out while two estimates
    # share one (docs/decisions/relocate-to-missing-in-large-rooms.md).
    relocate_to_missing: bool | None = None
    # Far relocation: such a target is first tried at the best point of the residual the
    # others leave at least the restarts' radius away from its spot, then where a target is
    # missing; and at K >= 2 the escape is always taken, since the test of a stuck fit
    # cannot see one (a power fit's noise level absorbs its misfit). None: the power model
    # in rooms with the dense dictionary (docs/decisions/power-model-search.md).
    relocate_far: bool | None = None
    # After the polish, each estimate whose profile (the others held, its gain free) fits
    # as well, within chi-square(2)'s 95 %, somewhere beyond the restarts' radius is tried
    # there as far relocation does, even when the fit does not look stuck: in rooms with few
    # LEDs per target the aggregated fit has such optima at noise-level costs. None: the
    # correlation model in rooms whose profiles are scanned
    # (docs/decisions/far-places-in-the-search.md).
    relocate_ambiguous: bool | None = None
    # The noise coefficient held at 0 while targets are inserted (freed in the refinements
    # after): the power model's noise atom (ones, nearly a signal direction) otherwise takes
    # the signal of the targets not yet inserted, and later insertions find no room for them
    # (the targets then run to the room's corners). None: the power model in rooms with the
    # dense dictionary (measured worse in large rooms; docs/decisions/power-model-search.md).
    grow_without_noise: bool | None = None
    # Restarts when the fit looks stuck, K known and K > 1. None: 0 with far relocation
    # (which finds what they find, at half their cost), else 1.
    restarts: int | None = None
    misfit_ratio: float = 1.5
    # Priors of the nuisance parameters (log units; None: not fitted). Each target's
    # amplitude gain (phones differ, are held differently) and the common power scale of the
    # measurement (pilots, receivers' calibration, units).
    log_gain_sd: float | None = 0.1
    log_scale_sd: float | None = 0.5
    # Prior sd of each component (tangent) of a terminal's unknown photodiode tilt, fitted
    # when terminals send their own amplitudes but not their normal (hand-held phones tilt)
    # and kept when significant; a layout's ``receiver_tilt_sd`` replaces it, and its tilts
    # are then always fitted. None: photodiodes held level.
    tilt_sd: float | None = 0.15
    # In the ``terminals`` form, when the terminals' residuals show the LEDs' own relative
    # errors (pilot amplitudes, beams off their data sheet) beyond the noise's chance, the
    # terminals are refitted with each amplitude weighted by its noise plus that error
    # (generalised least squares: the brightest LEDs carry the largest errors). False: one
    # weight for all (docs/decisions/led-errors-in-terminal-weights.md).
    terminal_led_weights: bool = True
    # In the ``terminals`` form, the first noise-weighted pass and the first survey-scatter
    # pass also start from the grid cells where their own weighted cost is lowest, not only
    # from the previous pass's optimum (docs/decisions/weighted-pass-starts.md). False: from
    # the previous optimum only.
    weighted_pass_starts: bool = True
    # The room's tolerances, fitted with the aggregated correlation as a last stage
    # (.gridless.tolerances; None: never): each LED's pilot amplitude (log sd) and half-power
    # angle (degrees), as LED data sheets give them, and optionally each target's photodiode
    # tilt (tangent sd, about radians; 0: not fitted, which measured better, see
    # docs/decisions/room-tolerance-stage.md). Tried only when the fit's whitened cost per degree
    # of freedom is
    # above ``tolerance_misfit_ratio`` and a score test promises enough; kept only when it
    # lowers that cost by more than its extra parameters' chi-square mean plus
    # ``tolerance_significance`` standard deviations (gridless.stages.with_room_tolerances).
    led_log_amplitude_sd: float | None = 0.05
    led_half_power_sd_deg: float = 3.0
    room_tilt_sd: float = 0.0
    # Where the tolerances are kept, the photodiodes' tilts are then fitted too, from the
    # joint optimum, with the layout's ``receiver_tilt_sd`` as their prior, else this one
    # (tangent sd, about radians: hand-held phones; 0.1 is 5.7 degrees per component,
    # between the realistic mix's 0-10 and the tilted condition's 0-20 degree ranges, 4.1 and 8.2),
    # unless
    # the layout says its photodiodes are level (``receivers_level``). Not gated as
    # ``tilt_sd``'s terminal fits are: the tilts lower the aggregated cost too little to tell
    # a tilted room from a level one. 0: not fitted (docs/decisions/tilts-after-tolerances.md).
    tolerance_tilt_sd: float = 0.1
    tolerance_misfit_ratio: float = 1.1
    # The score test passes when the first Gauss-Newton step promises more than this times
    # the extra parameters' count (a room as modelled promises about half of it).
    tolerance_score_ratio: float = 1.0
    tolerance_significance: float = 3.0
    # Where the tolerances are fitted, each target is also moved far (to the best grid point
    # at least half the LEDs' mean height away) and the joint fit keeps what lowers its cost,
    # as it does with the restarts' placements (.gridless.tolerances.GridMoves).
    tolerance_jumps: bool = True
    # A stage of nuisances is kept when it lowers the whitened cost by more than its extra
    # parameters' chi-square mean plus this many standard deviations.
    stage_significance: float = 3.0


@dataclass(frozen=True)
class LevenbergMarquardtSettings:
    """LM settings: inner iterations per insertion, starting damping, relative tolerance."""

    inner_iter: int
    initial_damping: float
    tol: float


# Per model: correlation takes few damped iterations at a loose tolerance (as accurate, far
# fewer evaluations); power has M values for 2K + 1 unknowns, a much flatter, multimodal
# cost, and keeps the careful settings (measured in docs/decisions/gridless-defaults.md).
LM_DEFAULTS: dict[Model, LevenbergMarquardtSettings] = {
    "correlation": LevenbergMarquardtSettings(inner_iter=2, initial_damping=1e-1, tol=1e-4),
    "power": LevenbergMarquardtSettings(inner_iter=4, initial_damping=1e-3, tol=1e-7),
}


def pick(chosen: _Number | None, default: _Number) -> _Number:
    """``chosen`` unless it is None."""
    return default if chosen is None else chosen


def nuisance_priors(layout: Layout, options: GridlessOptions) -> Priors:
    """The priors of a room: gains and scale from the options, heights from the layout's
    ``grid.receiver_height_sd`` (0: every target on the receivers' plane)."""
    mean = layout.grid.receiver_height
    spread = layout.grid.receiver_height_sd
    top = float(layout.led_positions[:, 2].min()) - _HEIGHT_CLEARANCE_M
    bounds = (max(0.0, mean - _HEIGHT_SPAN_SD * spread), min(top, mean + _HEIGHT_SPAN_SD * spread))
    gain_sd = None if options.free_weights else options.log_gain_sd
    scale_sd = None if gain_sd is None else options.log_scale_sd
    return Priors(gain_sd, scale_sd, spread, mean, bounds)


def diffuse_table(fingerprint: Fingerprint) -> DiffuseTable | None:
    """The fingerprint's interpolated diffuse reflections, None for a line-of-sight room."""
    return fingerprint.reflection_table()
