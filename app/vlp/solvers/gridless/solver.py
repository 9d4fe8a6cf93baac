"""The default solver: gridless (off-grid) localization by alternating descent conditional gradient.

ADCG (Boyd, Schiebinger and Recht, "The alternating descent conditional gradient method for
sparse inverse problems", SIAM J. Optim. 2017) applied to the aggregated VLP model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from ..._kernels import kernel_mode
from ...ambiguity import (
    covering_twins,
    far_optima,
    farthest_in_region,
    mirror_twins,
    reaching_beyond,
    twins_possible,
)
from ...fingerprints import Fingerprint
from ...measurements import Measurement, Model, noise_atom, summed_terminals
from ...scale import check_amplitude_scale
from ...simulation import mean_signal_power
from ...typing import FloatArray, IntArray
from ...uncertainty import (
    FITS_TO_NOISE,
    FitQuality,
    Misfit,
    MisfitDesign,
    assess_fit,
    bounded_covariances,
    fit_misfit,
    misfit_design,
    own_excess_widening,
    predictive_covariances,
)
from .._censored import censored_substitutes, with_censored_variance
from ..base import MAX_TARGETS, Solution, Solver, register_solver
from ._compiled.channel import channel_constants, channel_rows
from ._compiled.fit import correlation_profiles_kernel, correlation_scores_kernel
from ._compiled.search import growth_kernel, refine_kernel
from ._compiled.uncertainty import misfit_design_kernel, uncertainty_kernel
from .channel import ChannelKernel
from .lm import STEP_TOL_M
from .local import PowerScan, TerminalWindows
from .model import (
    MAX_LOG_SCALE,
    FitState,
    Objective,
    Priors,
    Whitening,
    _Slots,
    compiled_indices,
    gram,
    levenberg_marquardt,
    target_gains,
)
from .options import (
    LM_DEFAULTS,
    GridlessOptions,
    LevenbergMarquardtSettings,
    diffuse_table,
    nuisance_priors,
    pick,
)
from .terminals import TerminalFit, fit_terminal, starting_cells
from .tolerances import GridMoves, RoomTolerances, ToleranceFit, fit_room_tolerances
from .whitening_memo import MAX_KEPT_VALUES, WhiteningMemo, state_key

__all__ = ["LM_DEFAULTS", "GridlessOptions", "GridlessSolver"]

# Largest model-error design (observations x targets x LEDs) held for the covariance; a
# larger room falls back to the reduced chi-square's inflation.
_MAX_MISFIT_ENTRIES = 4_000_000
# Share of the terminals' residual sum of squares that the LEDs' relative errors must
# explain, in standard deviations of the noise's chi-square, for the terminals to be
# refitted with the LEDs' errors in their weights.
_LED_WEIGHT_SIGNIFICANCE = 3.0
# ... and the largest relative sd of an LED's error taken for one: data sheets bin flux
# within +-10-15 %; a larger estimate is a fit that does not hold (a terminal placed far
# off in a badly lit room), which the weights would make worse
# (docs/decisions/led-errors-in-terminal-weights.md).
_MAX_LED_ERROR_SD = 0.25
# A count read off the rank of R replaces a smaller count by energy only when its fit's
# variance ratio against that one is above this (GridlessSolver._explains_more).
_COUNT_F_RATIO = 10.0
# Largest gains matrix (M x N entries) whose grid the far-optimum scans read per answer
# (GridlessSolver._far_optima and _aggregated_far_optima; K x M x N per answer, M^2 N per
# target for the correlation).
_MAX_PROFILE_ENTRIES = 1_000_000
# Grid steps added to the reach of a local refinement (targets move a little while fitted).
_NEAR_MARGIN_STEPS = 4.0
# No points to avoid (the compiled growth step takes an (n, 2) array).
_NO_POINTS = np.zeros((0, 2))


def _search_state(state: FitState) -> tuple[Any, ...]:
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


class _Search(NamedTuple):
    """One nominal search (GridlessSolver._search): its run, its fit, the restarts' optima
    it did not pick and the common scale it ran at."""

    run: _Run
    state: FitState
    others: list[FloatArray]
    prescale: float


@dataclass
class _Run:
    """Per-call state (solver objects are shared between threads, so nothing lives on self)."""

    values: FloatArray
    priors: Priors
    iterations: int = 0
    # Objectives built for this run, by (whitening, priors, ceiling) (see
    # GridlessSolver._objective).
    objectives: dict[tuple[int, int, float], tuple[Whitening, Priors, Objective]] = field(
        default_factory=dict, repr=False
    )
    # Profiles computed for this run's values, by the state's and the priors in force
    # (GridlessSolver._profiles): the search's last polish and the answer's far places
    # often ask for the same.
    profiles: dict[tuple[bytes, Priors], tuple[FloatArray, FloatArray]] = field(
        default_factory=dict, repr=False
    )
    # Each state's plug-in whitening and whitened residual, likewise
    # (GridlessSolver._whitened_residual): the escape tests and the profiles of one polished
    # fit ask for them up to four times.
    whitened: dict[tuple[bytes, Priors], tuple[Whitening, FloatArray]] = field(
        default_factory=dict, repr=False
    )


_NO_FIT_TEST = (
    "the power model cannot tell its noise from its signal, so its chi-square is no test of "
    "the model (the 95 % radii use the scatter of its residuals); send the correlation "
    "matrix or each terminal's amplitudes for one"
)


def _response_covariances(
    normal: FloatArray,
    rows: FloatArray,
    columns: FloatArray,
    index: IntArray,
    sd: float,
) -> FloatArray:
    """Covariances (K, 2, 2) of the positions a Gauss-Newton fit moves when its whitened
    model moves by ``columns @ t`` (L, n) with ``t`` i.i.d. of standard deviation ``sd``:
    ``sd^2 G G^T`` over the rows ``index`` (K, 2) of ``G = normal^+ rows columns`` (``rows``
    the Jacobian's transpose, (P, L))."""
    moved = np.linalg.pinv(normal, hermitian=True) @ (rows @ columns)  # (P, n)
    positions = moved[index]  # (K, 2, n)
    return np.asarray(sd**2 * positions @ positions.transpose(0, 2, 1))


def _misfit_design(
    jacobian: FloatArray, normal: FloatArray, columns: list[FloatArray]
) -> MisfitDesign:
    """:func:`app.vlp.uncertainty.misfit_design` (its reference), in one compiled call with
    the compiled kernels."""
    if kernel_mode() != "compiled":
        return misfit_design(jacobian, normal, columns)
    sizes = np.array([block.shape[1] for block in columns], dtype=np.int64)
    side_by_side = np.ascontiguousarray(np.hstack(columns), dtype=np.float64)
    return MisfitDesign(
        *misfit_design_kernel(
            np.ascontiguousarray(jacobian, dtype=np.float64),
            np.ascontiguousarray(normal, dtype=np.float64),
            side_by_side,
            sizes,
        )
    )


@register_solver
class GridlessSolver(Solver):
    """Off-grid localization: insert a target at the best grid point, refine all, repeat.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}
    options : GridlessOptions, default=None
        Tuning knobs and priors (defaults: see :class:`GridlessOptions`).

    Notes
    -----
    Model (normalised units, see :mod:`.gridless.model`):
    ``y = sum_k w_k e^(v + 2 u_k) phi(g(p_k, z_k)) + s a`` with ``phi(g) = vech(g g^T)``
    (correlation) or ``g o g`` (power), ``a`` the noise atom (``E[R] = sum_k g_k g_k^T +
    K sigma^2 I``), ``g`` the line of sight plus the room's interpolated diffuse reflections,
    ``u_k`` each target's log amplitude gain, ``v`` the common log power scale and ``z_k``
    its height. The loop (ADCG, Boyd, Schiebinger and Recht, SIAM J. Optim. 27(2), 2017):

    1. *Insert* a target at the grid point that most lowers the (whitened) cost,
       ``argmax_j 2 w <c psi_j, r> - w^2 ||c psi_j||^2`` (dense dictionary for small rooms,
       the matrix-free ``Psi^T`` and plain residual for large ones).
    2. *Refine* all positions and ``s`` jointly with projected Levenberg-Marquardt on the
       continuous channel model (analytic gradients; positions clipped to the room), for
       ``inner_iter`` iterations (:data:`LM_DEFAULTS`; ``count_inner_iter`` when K is
       being counted). Gains, scale and heights stay fixed while targets are inserted, and
       so does the power model's noise coefficient, at 0 (``grow_without_noise``: its atom
       of ones would take the signal of the targets not yet inserted).
    3. After K insertions: LM rounds whitened by the plug-in covariance of the aggregated
       noise (``Cov <A, R> = 4 sigma^2 tr(A M0 A)``, ``M0 = S + K sigma^2 / 2 I``,
       ``sigma^2 = s / K``; exact and O(M^3) in the eigenbasis of ``M0``).
    4. Escapes, only when the fit looks stuck (:meth:`_needs_escape`): one pass of
       *relocation* moves (in large rooms also to where a target is missing), then, with
       K known and K > 1, ``restarts`` more runs whose first insertion avoids the earlier
       ones'; the lowest plain cost wins. The power model in small rooms relocates far
       instead, always from K = 2 (``relocate_far``: its fitted noise level hides a stuck
       fit), with no restarts.
    5. Nuisances in stages (:meth:`_with_nuisances`): the common scale and the heights
       (when ``grid.receiver_height_sd`` > 0), then each target's gain, each with a
       Gaussian prior (:class:`GridlessOptions`), kept only when a score test and then the
       fit show a decrease beyond the chance level of their extra parameters. Free
       weights instead of priors let a close pair merge into one target of weight 2.
       Then, for the correlation model at K >= 2, the LEDs' tolerances (each LED's
       amplitude and beam width, with data-sheet priors) in a joint fit, kept on the same
       kind of test when the fit shows a misfit (:meth:`_with_room_tolerances`). The joint
       fit then tries long moves of each target and the restarts' placements, and keeps
       those that lower its cost: it tells apart optima the nominal model cannot.
    6. Uncertainty (:meth:`_uncertainty`): the sandwich covariance of the final whitened
       fit with the noise and the model errors it does not fit (each target's relative
       amplitude error per LED, its photodiode's tilt, its height when not fitted), whose
       variances are estimated from the residuals net of what the fit absorbed and widened
       for their degrees of freedom (:mod:`app.vlp.uncertainty`); and the fit's quality
       (:func:`app.vlp.uncertainty.assess_fit`). Each radius also holds what a curvature
       cannot see: another place where the estimate, the others held, fits about as well
       (:meth:`_aggregated_far_optima`), or its mirror image across a line of LEDs
       (:meth:`_reported`).

    With K known the measurement is first divided by a guessed common scale when its power
    per target is more than 1.5x off the room's mean (:meth:`_prescale`). Unknown K: first
    read off the correlation matrix's rank (``count_by_rank``,
    :func:`app.vlp.measurements.summed_terminals`): ``R = sum_k a_k a_k^T`` over K < M
    terminals has rank K exactly. Where the spectrum does not say (the power model, a matrix
    that is no such sum), targets are added one at a time; a state with more targets is
    kept when its plain cost is below the best so far by ``count_threshold`` times the
    energy ``||phi(p)||^2`` of the targets it adds, trying up to ``count_lookahead`` more
    before stopping. Terminals that send
    their own amplitudes are fitted one by one (:meth:`solve_terminals`).

    The stages in order, what each estimates and why each gate sits where it does:
    ``docs/explanation/solver.md`` (its section names are quoted below).

    Accuracy, counting and speed are measured by ``bench/accuracy.py``,
    ``bench/real_rooms.py``, ``bench/tune_gridless.py``, ``bench/solver_timing.py`` and
    ``bench/solve_loop.py`` (instruction counts); the figures are in ``docs/results/accuracy.md``,
    ``docs/results/real-rooms.md`` and ``docs/results/solver-timing.md``.

    Examples
    --------
    >>> from app.vlp.fingerprints import build_fingerprint
    >>> from app.vlp.measurements import measurement_from_amplitudes
    >>> from app.vlp.presets import paper_layout
    >>> from app.vlp.simulation import true_amplitudes
    >>> layout = paper_layout()
    >>> solver = GridlessSolver(build_fingerprint(layout), "correlation")
    >>> truth = np.array([[0.93, 1.41], [2.72, 3.05]])
    >>> amps = true_amplitudes(layout, truth)
    >>> solution = solver.solve(measurement_from_amplitudes(amps, "correlation", 16), 2)
    >>> np.round(solution.positions[np.argsort(solution.positions[:, 0])], 3).tolist()
    [[0.93, 1.41], [2.72, 3.05]]
    """

    name = "gridless"
    description = "off-grid ADCG with whitened Levenberg-Marquardt refinement (default)"

    def __init__(
        self, fingerprint: Fingerprint, model: Model, options: GridlessOptions | None = None
    ) -> None:
        super().__init__(fingerprint, model)
        self.options = options or GridlessOptions()
        defaults = LM_DEFAULTS[model]
        self._lm = LevenbergMarquardtSettings(
            inner_iter=pick(self.options.inner_iter, defaults.inner_iter),
            initial_damping=pick(self.options.initial_damping, defaults.initial_damping),
            tol=pick(self.options.lm_tol, defaults.tol),
        )
        layout = fingerprint.layout
        self._scale = float(np.sqrt(mean_signal_power(fingerprint)))
        self._kernel = ChannelKernel(layout, self._scale, diffuse_table(fingerprint))
        # The power model has M values for 2K + 1 unknowns and a poorly identified noise
        # level (its noise atom is nearly a signal direction): its whitened statistics cannot
        # tell a freed nuisance from noise (an ideal room freed the scale in many K = 1 solves
        # and lost accuracy), so nuisances are fitted for correlation (and terminals).
        self._priors = nuisance_priors(
            layout,
            self.options if model == "correlation" else replace(self.options, log_gain_sd=None),
        )
        self._growth_priors = Priors(height_mean=self._priors.height_mean)
        # The covariance's noise variance, whitened: at most the whitening's own (1) where
        # the noise atom measures the noise (correlation: the diagonal of R); free for the
        # power model, whose noise atom (ones) is nearly a signal direction, so its fitted
        # noise level says nothing (0 in a third of ideal-room fits, several times the
        # truth in others) and only the residuals' scatter measures the noise.
        self._noise_identified = model == "correlation"
        self._max_noise = 1.0 if self._noise_identified else math.inf
        # Nuisances are freed in stages: the common scale and the heights, then the gains.
        full = self._priors
        scale_and_heights = replace(full, log_gain_sd=None)
        self._stages = [
            stage
            for stage in (scale_and_heights, full)
            if _Slots.make(1, stage, self.options.free_weights).size
            > _Slots.make(1, self._growth_priors, self.options.free_weights).size
        ]
        if len(self._stages) == 2 and self._stages[0] == self._stages[1]:
            self._stages.pop()
        # Whitenings already computed, by state values (.gridless.whitening_memo).
        self._whitenings = WhiteningMemo()
        # Plain least squares (one object: the compiled kernels keep their view of it).
        self._identity = Whitening.identity(model, fingerprint.n_leds)
        self._centres = layout.cell_centres()
        self._led_xy = np.ascontiguousarray(layout.led_positions[:, :2])
        self._dense = fingerprint.is_dense
        # Photodiodes the layout says face straight up: no tilt to fit or allow for.
        self._receivers_level = layout.grid.receivers_level
        # Most rooms have no mirror twins anywhere: their answers skip the check (decided
        # here, once, in dense rooms; large ones check every answer).
        floor = layout.room
        self._twins_possible = not self._dense or twins_possible(
            self._centres, self._led_xy, self._gains_at, (floor.length, floor.width)
        )
        self._relocate_to_missing = (
            not self._dense
            if self.options.relocate_to_missing is None
            else self.options.relocate_to_missing
        )
        self._relocate_far = (
            model == "power" and self._dense
            if self.options.relocate_far is None
            else self.options.relocate_far
        )
        self._grow_without_noise = (
            model == "power" and self._dense
            if self.options.grow_without_noise is None
            else self.options.grow_without_noise
        )
        self._restarts = pick(self.options.restarts, 0 if self._relocate_far else 1)
        # Restarts begin away from earlier first insertions, by half the mean LED height
        # above the receivers (about the size of one LED's bright spot).
        heights = layout.led_positions[:, 2] - layout.grid.receiver_height
        self._avoid_radius = 0.5 * float(np.mean(heights))
        n_obs = (
            fingerprint.n_leds
            if model == "power"
            else fingerprint.n_leds * (fingerprint.n_leds + 1) // 2
        )
        self._upper_lower = (
            (
                np.arange(fingerprint.n_leds),
                np.arange(fingerprint.n_leds),
            )
            if model == "power"
            else np.triu_indices(fingerprint.n_leds)
        )
        # Each target costs 2 coordinates and the noise power one more unknown.
        self._max_count = max(1, min(MAX_TARGETS, fingerprint.n_cells, (n_obs - 1) // 2))
        # The far-place scans read every grid point per answer: dense rooms small enough.
        self._scans_profiles = (
            self._dense and fingerprint.n_leds * fingerprint.n_cells <= _MAX_PROFILE_ENTRIES
        )
        self._relocate_ambiguous = self._scans_profiles and (
            model == "correlation"
            if self.options.relocate_ambiguous is None
            else self.options.relocate_ambiguous
        )
        if self._dense:
            self._gains = np.ascontiguousarray(
                fingerprint.dense_scaled_gains() / self._scale, dtype=np.float64
            )
            self._gains_sq = self._gains**2
            self._gains_fourth = self._gains_sq**2
            self._column_energy = np.maximum(self._gains_sq.sum(axis=0), 1e-300)
        else:
            self._gains_sparse = fingerprint.scaled_gains() / self._scale
            if model == "power":  # the correlation model scans through the operator
                self._gains_sq_sparse = self._gains_sparse.power(2)
            self._operator = fingerprint.correlation_operator()
            total = np.asarray(self._gains_sparse.power(2).sum(axis=0)).ravel()
            fourth = np.asarray(self._gains_sparse.power(4).sum(axis=0)).ravel()
            self._psi_norms = np.sqrt(0.5 * (total**2 + fourth))
            self._fourth_sums = fourth
            self._column_energy = np.maximum(total, 1e-300)
        self._mean_column_energy = float(np.mean(self._column_energy))
        # Large rooms: terminals are started near their own footprint (see ._local), as wide
        # as on the floor (a terminal may send its own height, down to 0).
        self._windows = None if self._dense else TerminalWindows.build(fingerprint, 0.0)
        if self._windows is not None and not self._windows.is_useful():
            self._windows = None
        # Large rooms (the terminals' rule: windows much smaller than the room), power model:
        # a refinement after an insertion or a relocation moves only the targets that can
        # share an LED with the changed ones (see :meth:`_fit_near`). Two receivers on the
        # plane share an LED only within twice the footprint radius of each other.
        self._near_reach: float | None = None
        if self._windows is not None and model == "power":
            drop = float(layout.led_positions[:, 2].max()) - layout.grid.receiver_height
            radius = drop * math.tan(math.radians(layout.receiver.fov_deg))
            self._near_reach = 2.0 * radius + _NEAR_MARGIN_STEPS * layout.grid.step
        # Large rooms, power model: insertion scans score only the tiles that can hold the
        # best point (see ._local.PowerScan; the same argmax as scoring all N).
        self._power_scan = (
            PowerScan.build(fingerprint, self._scale, self._fourth_sums)
            if not self._dense and model == "power" and not self.options.free_weights
            else None
        )
        # The search's growth and refinement steps as one compiled call each
        # (:meth:`_grow_compiled`, :meth:`_refine_compiled`): their constants (the channel's,
        # the search priors' tuples, the entries' diagonal indicator), and their bounds per
        # noise ceiling and K.
        self._search_constants: tuple[Any, ...] | None = None
        self._search_objectives: dict[float, Objective] = {}
        constants = channel_constants(self._kernel)
        if (
            model == "correlation"
            and self._dense
            and self._near_reach is None
            and not self.options.free_weights
            and constants is not None
        ):
            search = self._search_objective(math.inf)
            one = FitState.empty().with_target(np.zeros(2), self._growth_priors.height_mean)
            _, search_layout, search_priors = search.compiled_state(one)
            _, _, is_diag = compiled_indices(model, fingerprint.n_leds)
            self._search_constants = (*constants, search_layout, search_priors, is_diag)
        # The faintest (5th percentile: corners out of view aside) and brightest grid points.
        self._energy_band = (
            float(np.percentile(self._column_energy, 5.0)),
            float(np.max(self._column_energy)),
        )

    # -- insertion ---------------------------------------------------------------------
    def _correlations(
        self, white: Whitening, residual: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """``<c psi_j, r>`` and ``||c psi_j||^2`` for every grid point j, shapes (N,)."""
        n_leds = self.fingerprint.n_leds
        weighted = white.weights * residual
        if self.model == "power":
            if self._dense:
                num = weighted @ self._gains_sq
                norms = (white.weights**2) @ self._gains_fourth
            else:
                g2 = self._gains_sq_sparse
                num = g2.T @ weighted
                if white.rotation is None and np.all(white.weights == white.weights[0]):
                    # Plain metric (large rooms score this way): sum_i g_ij^4, kept once.
                    norms = white.weights[0] ** 2 * self._fourth_sums
                else:
                    norms = g2.power(2).T @ white.weights**2
            return np.asarray(num), np.asarray(norms)
        if self._dense and kernel_mode() == "compiled":
            num, norms = correlation_scores_kernel(
                white.compiled(), np.ascontiguousarray(residual, dtype=np.float64), self._gains
            )
            return num, norms
        half = np.zeros((n_leds, n_leds))
        half[white.upper, white.lower] = weighted
        sym = 0.5 * (half + half.T)
        if white.rotation is not None:
            sym = white.rotation @ sym @ white.rotation.T
        if self._dense:
            gains = self._gains
            num = np.einsum("mj,mj->j", gains, sym @ gains)
            rot = white.rotate(gains)
            c2 = np.zeros((n_leds, n_leds))
            c2[white.upper, white.lower] = white.weights**2
            c2 = 0.5 * (c2 + c2.T)
            sq = rot**2
            norms = np.einsum("mj,mj->j", sq, c2 @ sq)
        else:
            # The operator's adjoint halves off-diagonal entries: pass 2 Q_il above the diagonal.
            upper, lower = np.triu_indices(n_leds)
            vech_q = np.where(upper == lower, 1.0, 2.0) * sym[upper, lower]
            num = self._operator.rmatvec(vech_q) / self._scale**2
            norms = self._psi_norms**2
        return np.asarray(num), np.asarray(norms)

    def _scores(self, white: Whitening, residual: FloatArray, weight: float) -> FloatArray:
        """Decrease of the whitened cost if a target of ``weight`` were added at each grid point.

        ``2 w <c psi_j, r> - w^2 ||c psi_j||^2`` for fixed weights; the normalised correlation
        ``<c psi_j, r> / ||c psi_j||`` for free weights.
        """
        num, norms_sq = self._correlations(white, residual)
        if self.options.free_weights:
            return np.asarray(num / np.sqrt(np.maximum(norms_sq, 1e-300)))
        return np.asarray(2.0 * weight * num - weight**2 * norms_sq)

    # -- main loop -----------------------------------------------------------------------
    def _whitening(self, state: FitState) -> Whitening:
        if not self.options.whiten or state.n_targets == 0:
            return self._identity
        return self._whitenings.get(state, self._plug_in)

    def _plug_in(self, state: FitState) -> Whitening:
        return Whitening.from_state(self.model, self._kernel, state, float(state.n_targets))

    def _objective(
        self, run: _Run, white: Whitening, nuisance: bool = True, ceiling: float = math.inf
    ) -> Objective:
        """The run's objective in ``white``'s metric, its noise coefficient at most
        ``ceiling`` (one per whitening, priors and ceiling: a solve asks for the same one many
        times, and an Objective keeps its compiled form)."""
        priors = run.priors if nuisance else self._growth_priors
        key = (id(white), id(priors), ceiling)
        known = run.objectives.get(key)
        if known is not None and known[0] is white and known[1] is priors:
            return known[2]
        objective = Objective(
            self._kernel, white, run.values, self.options.free_weights, priors, ceiling
        )
        if white.weights.shape[0] <= MAX_KEPT_VALUES:  # a large room's are computed afresh
            if len(run.objectives) >= 256:
                run.objectives.clear()
            run.objectives[key] = (white, priors, objective)
        return objective

    def _fit(
        self,
        run: _Run,
        white: Whitening,
        state: FitState,
        max_iter: int,
        nuisance: bool = True,
        around: FloatArray | None = None,
        ceiling: float = math.inf,
    ) -> tuple[FitState, float]:
        """LM refinement of all targets, or, with ``around`` (points, shape (n, 2), metres)
        in a large room, of the targets near those points only (:meth:`_fit_near`); the
        noise coefficient at most ``ceiling``."""
        if around is not None:
            near = self._fit_near(run, white, state, max_iter, nuisance, around, ceiling)
            if near is not None:
                return near
        state, cost, used = levenberg_marquardt(
            self._objective(run, white, nuisance, ceiling),
            state,
            max_iter=max_iter,
            initial_damping=self._lm.initial_damping,
            tol=self._lm.tol,
        )
        run.iterations += used
        # Per state, not per call: the answer reports the run that produced the state it
        # returns, not whichever candidate was fitted last.
        state.converged = used < max_iter
        return state, cost

    def _fit_near(
        self,
        run: _Run,
        white: Whitening,
        state: FitState,
        max_iter: int,
        nuisance: bool,
        around: FloatArray,
        ceiling: float = math.inf,
    ) -> tuple[FitState, float] | None:
        """LM over the positions of the targets within reach of ``around`` and the noise
        coefficient, the other targets held where they are; None when that is not the
        whole-room fit's cost with fewer parameters (a small room, nuisance parameters, a
        target off the receivers' plane) or when every target is near.

        The cost is the whole room's: the held targets' atoms are subtracted from the
        measurement, exactly. In a large room they share no LED with the changed targets,
        so their part of the gradient did not change; the final joint polish refines all.
        """
        reach = self._near_reach
        k = state.n_targets
        priors = run.priors if nuisance else self._growth_priors
        if (
            reach is None
            or k < 2
            or _Slots.make(k, priors, self.options.free_weights).size != 2 * k + 1
            or not bool(np.all(state.heights == self._kernel.receiver_height))
        ):
            return None
        offsets = state.positions[:, None, :] - np.asarray(around)[None, :, :]
        active = np.min(np.sum(offsets**2, axis=2), axis=1) <= reach**2
        if bool(active.all()):
            return None
        held = state.subset(~active)
        held.noise = 0.0
        # values - sum over the held targets of w_k phi(g(p_k)), plain units (s = 0).
        plain = Objective(
            self._kernel, self._identity, run.values, self.options.free_weights, Priors()
        )
        rest = plain.residual(plain.pack(held), held)
        objective = Objective(
            self._kernel,
            white,
            rest,
            self.options.free_weights,
            priors,
            ceiling,
        )
        fitted, cost, used = levenberg_marquardt(
            objective,
            state.subset(active),
            max_iter=max_iter,
            initial_damping=self._lm.initial_damping,
            tol=self._lm.tol,
        )
        run.iterations += used
        positions = state.positions.copy()
        positions[active] = fitted.positions
        merged = FitState(
            positions,
            state.weights,
            fitted.noise,
            state.heights,
            state.log_gains,
            state.log_scale,
        )
        merged.converged = used < max_iter
        return merged, cost

    def _refine(self, run: _Run, state: FitState, max_iter: int, rounds: int) -> FitState:
        """LM rounds, each whitened by the covariance plugged in from the previous one."""
        if state.n_targets > 0 and self._compiled_search(run):
            return self._refine_compiled(run, state, max_iter, rounds)
        for round_index in range(max(rounds, 1)):
            before = run.iterations
            state, _ = self._fit(run, self._whitening(state), state, max_iter)
            if round_index > 0 and run.iterations - before <= 2:
                break  # the re-whitened metric no longer moves the fit
        return state

    def _residual(self, run: _Run, white: Whitening, state: FitState) -> FloatArray:
        if state.n_targets == 0:
            return white.data(run.values)
        return self._objective(run, white).data_cost(state)[1]

    def _insert(
        self, run: _Run, state: FitState, white: Whitening, avoid: FloatArray | None = None
    ) -> FitState:
        """Add a unit-weight target at the grid point that most lowers the cost (not within
        ``_avoid_radius`` of the points ``avoid``, shape (n, 2), when given)."""
        if not self._dense:
            # Large rooms score with the plain residual: whitened atom norms would need the
            # rotated gains of every grid point.
            white = self._identity
        residual = self._residual(run, white, state)
        if self._power_scan is not None and (avoid is None or avoid.shape[0] == 0):
            found = self._power_scan.best(
                residual, math.exp(state.log_scale), float(white.weights[0]) ** 2
            )
            if found is not None:
                return state.with_target(self._centres[found[0]], self._priors.height_mean)
        scores = self._scores(white, residual, math.exp(state.log_scale))
        if avoid is not None and avoid.shape[0] > 0:
            allowed = scores.copy()
            for point in avoid:
                near = np.sum((self._centres - point) ** 2, axis=1) < self._avoid_radius**2
                allowed[near] = -np.inf
            if np.isfinite(allowed).any():
                scores = allowed
        best = int(np.argmax(scores))
        return state.with_target(self._centres[best], self._priors.height_mean)

    def _needs_escape(self, run: _Run, state: FitState) -> bool:
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
        if self._relocate_far and state.n_targets >= 2:
            return True
        white, residual, within = self._noise_test(run, state)
        # With no degree of freedom left (power model, 2K + 1 >= M) no cost tells a local
        # minimum from the truth: always escaping doubles the time there but is worth about
        # 8 % of the error (docs/explanation/uncertainty.md#the-fits-quality).
        if not within:
            return True
        if not self._dense:
            white = self._identity
            residual = self._residual(run, white, state)
        weight = math.exp(state.log_scale)
        if self._power_scan is not None:
            found = self._power_scan.best(residual, weight, float(white.weights[0]) ** 2)
            if found is not None:
                _, gain_best, norm_best = found
                return bool(gain_best > self.options.count_threshold * weight**2 * norm_best)
        num, norms_sq = self._correlations(white, residual)
        gain = 2.0 * weight * num - weight**2 * norms_sq
        best = int(np.argmax(gain))
        return bool(gain[best] > self.options.count_threshold * weight**2 * norms_sq[best])

    def _noise_test(self, run: _Run, state: FitState) -> tuple[Whitening, FloatArray, bool]:
        """The state's whitening and whitened residual, and whether that residual is within
        ``misfit_ratio`` times its degrees of freedom (False with none left): a complete fit
        leaves only noise, about one unit per degree of freedom."""
        white, residual = self._whitened_residual(run, state)
        dof = residual.shape[0] - 2 * state.n_targets - 1
        within = dof > 0 and float(residual @ residual) <= self.options.misfit_ratio * dof
        return white, residual, bool(within)

    def _whitened_residual(self, run: _Run, state: FitState) -> tuple[Whitening, FloatArray]:
        """The state's plug-in whitening and its whitened residual of the run's values, kept
        per run, state values and priors (read only: callers do not write to them)."""
        key = (state_key(state), run.priors)
        known = run.whitened.get(key)
        if known is None:
            white = self._whitening(state)
            known = run.whitened[key] = (white, self._residual(run, white, state))
        return known

    def _fits_to_noise(self, run: _Run, state: FitState) -> bool:
        """Whether the fit leaves only noise (:meth:`_noise_test`): the profiles'
        likelihood-ratio regions then measure the noise, not a room that differs from its
        model (where a far move that lowers the cost follows the misfit, e.g. of a
        terminal's gain, not a target)."""
        return self._noise_test(run, state)[2]

    def _plain_cost(self, run: _Run, state: FitState) -> float:
        residual = self._residual(run, self._identity, state)
        return float(residual @ residual)

    def _atom_energy(self, position: FloatArray, weight: float) -> float:
        g2 = self._kernel.stacked(position[None, :], with_gradients=False)[:, 0] ** 2
        if self.model == "power":
            return float(weight**2 * (g2 @ g2))
        return float(weight**2 * 0.5 * (g2.sum() ** 2 + g2 @ g2))

    def _grow(
        self, run: _Run, state: FitState, inner_iter: int, avoid: FloatArray | None = None
    ) -> FitState:
        """One ADCG step: insert at the best grid point, then refine everything (briefly,
        in the metric of the state before the insertion), with ``grow_without_noise`` the
        noise coefficient held at 0."""
        if self._compiled_search(run):
            return self._grow_compiled(run, state, inner_iter, avoid)
        white = self._whitening(state)
        grown = self._insert(run, state, white, avoid)
        if inner_iter > 0:
            # Gains, scale and heights stay put while targets are being inserted: free, the
            # first targets would take the energy of those not yet inserted.
            grown, _ = self._fit(
                run,
                white,
                grown,
                inner_iter,
                nuisance=False,
                around=grown.positions[-1:],
                ceiling=0.0 if self._grow_without_noise else math.inf,
            )
        return grown

    def _compiled_search(self, run: _Run) -> bool:
        """Whether :meth:`_grow` and :meth:`_refine` run as one compiled call each
        (:mod:`.gridless._compiled.search`): the correlation model in a dense room, searching
        (positions and noise only), fixed weights, the compiled kernels in use."""
        return (
            self._search_constants is not None
            and run.priors is self._growth_priors
            and kernel_mode() == "compiled"
        )

    def _grow_compiled(
        self,
        run: _Run,
        state: FitState,
        inner_iter: int,
        avoid: FloatArray | None,
        n_targets: int | None = None,
    ) -> FitState:
        """:meth:`_grow` in one compiled call, or with ``n_targets`` the steps up to that
        many targets (the first one away from ``avoid``), as :meth:`_fit_known` takes them
        (the same kernels, in the same order: the same state to the bit). The states'
        whitenings are computed there, not kept: a growth step's state is never whitened
        again (the next step adds a target), but for the last state of a count, which the
        polish whitens once more."""
        k = state.n_targets
        ceiling = 0.0 if self._grow_without_noise else math.inf
        problem = (
            *self._search_problem(run),
            _search_state(state),
            self._gains,
            self._centres,
            _NO_POINTS if avoid is None else np.ascontiguousarray(avoid, dtype=np.float64),
            self._avoid_radius,
        )
        # One step, or the steps up to n_targets: the bounds say how many targets to reach.
        target_count = k + 1 if n_targets is None else n_targets
        positions, noise, total, used = growth_kernel(
            *problem, *self._search_objective(ceiling).bounds(target_count), inner_iter
        )
        added = positions.shape[0] - k
        grown = FitState(
            positions,
            np.concatenate((state.weights, np.ones(added))),
            float(noise),
            np.concatenate((state.heights, np.full(added, self._priors.height_mean))),
            np.concatenate((state.log_gains, np.zeros(added))),
            state.log_scale,
        )
        if inner_iter > 0:
            run.iterations += int(total)
            grown.converged = used < inner_iter
        return grown

    def _refine_compiled(self, run: _Run, state: FitState, max_iter: int, rounds: int) -> FitState:
        """:meth:`_refine` in one compiled call (the same kernels, in the same order: the
        same state to the bit; the rounds' whitenings are not kept, no later step asks for
        them)."""
        lower, upper = self._search_objective(math.inf).bounds(state.n_targets)
        positions, noise, total, last = refine_kernel(
            *self._search_problem(run), _search_state(state), lower, upper, rounds, max_iter
        )
        run.iterations += int(total)
        refined = FitState(
            positions, state.weights, float(noise), state.heights, state.log_gains, state.log_scale
        )
        refined.converged = last < max_iter
        return refined

    def _search_problem(self, run: _Run) -> tuple[Any, ...]:
        """The compiled search steps' ``(channel, table, search)`` for ``run``
        (:func:`.gridless._compiled.search.growth_kernel`)."""
        assert self._search_constants is not None
        channel, table, layout, priors, is_diag = self._search_constants
        search = (
            self._identity.compiled(),
            self.options.whiten,
            is_diag,
            run.values,
            self._kernel.receiver_height,
            layout,
            priors,
            self._lm.initial_damping,
            self._lm.tol,
            STEP_TOL_M,
        )
        return channel, table, search

    def _search_objective(self, ceiling: float) -> Objective:
        """An objective of the search priors with the noise at most ``ceiling``, for its
        parameter layout and bounds (its data are never read)."""
        found = self._search_objectives.get(ceiling)
        if found is None:
            found = self._search_objectives[ceiling] = Objective(
                self._kernel,
                self._identity,
                np.zeros(self._identity.weights.shape[0]),
                self.options.free_weights,
                self._growth_priors,
                ceiling,
            )
        return found

    def _count_and_fit(self, run: _Run) -> FitState:
        """Grow one target at a time while each brings its own energy (unknown K;
        docs/explanation/solver.md, "Counting").

        A real target removes about its own atom energy ``||phi(p)||^2`` from the plain
        residual; a spurious one, of unit weight, adds about as much. A state with more
        targets is kept when its cost is below the best so far by ``count_threshold`` times
        the energy of the targets it adds; up to ``count_lookahead`` more are tried before
        stopping (a close pair is often only resolved one target later).
        """
        opts = self.options
        state = FitState.empty()
        best, best_cost = state, self._plain_cost(run, state)
        while state.n_targets < self._max_count:
            state = self._grow(run, state, opts.count_inner_iter)
            state_cost = self._plain_cost(run, state)
            extra = state.n_targets - best.n_targets
            weights = state.effective_weights()[-extra:]
            energy = sum(
                self._atom_energy(p, float(w))
                for p, w in zip(state.positions[-extra:], weights, strict=True)
            )
            if best_cost - state_cost >= opts.count_threshold * energy:
                best, best_cost = state, state_cost
            elif extra > opts.count_lookahead:
                break
        if best.n_targets == 0:
            # Nothing brings its own energy (noise only): still answer one best guess.
            best = self._grow(run, best, opts.count_inner_iter)
        return best

    def _relocate(
        self,
        run: _Run,
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
        far = self._relocate_far if far is None else far
        moved = False
        step = self.fingerprint.layout.grid.step
        n_targets = state.n_targets
        white = self._whitening(state)
        cost = self._objective(run, white).cost(state)[0]
        missing: FloatArray | None = None
        for k in range(n_targets) if targets is None else targets:
            keep = np.arange(n_targets) != k
            others = state.subset(keep)
            own = state.positions[k]
            candidate = self._insert(run, others, white)
            tries = [candidate]
            if np.linalg.norm(candidate.positions[-1] - own) <= 1.5 * step:
                tries = []
                if far:
                    tries.append(self._insert(run, others, white, avoid=own[np.newaxis]))
                if self._relocate_to_missing or far:
                    if missing is None:
                        missing = self._insert(run, state, white).positions[-1]
                    if all(
                        np.linalg.norm(missing - point) > 1.5 * step
                        for point in [own, *(tried.positions[-1] for tried in tries)]
                    ):
                        tries.append(others.with_target(missing, self._priors.height_mean))
            for candidate in tries:
                # The moved target's old and new neighbourhoods (large rooms; all targets
                # else).
                changed = np.vstack((candidate.positions[-1:], state.positions[k : k + 1]))
                candidate, candidate_cost = self._fit(
                    run, white, candidate, self.options.final_iter, around=changed
                )
                if candidate_cost < cost:
                    # Keep the original order: the moved target takes slot k.
                    order = np.insert(np.arange(n_targets - 1), k, n_targets - 1)
                    state = candidate.reordered(order)
                    cost, moved = candidate_cost, True
                    missing = None
                    break
        return state, moved

    def _polish(self, run: _Run, state: FitState) -> FitState:
        """Whitened refinement rounds, then relocation passes while the fit looks stuck,
        then (``relocate_ambiguous``) far relocation of the estimates that fit as well far
        away."""
        opts = self.options
        state = self._refine(run, state, opts.final_iter, opts.whiten_rounds)
        for _ in range(opts.relocate_passes):
            if not self._needs_escape(run, state):
                break
            state, moved = self._relocate(run, state)
            if not moved:
                break
            state = self._refine(run, state, opts.final_iter, 1)
        if self._relocate_ambiguous and state.n_targets >= 2 and self._fits_to_noise(run, state):
            explained, best = self._profiles(run, state)
            ambiguous = reaching_beyond(
                explained, best, self._centres, state.positions, self._avoid_radius
            )
            if ambiguous.size:
                state, moved = self._relocate(run, state, far=True, targets=ambiguous)
                if moved:
                    state = self._refine(run, state, opts.final_iter, 1)
        return state

    def _fit_known(self, run: _Run, n_targets: int, avoid: FloatArray) -> FitState:
        """Greedy growth to ``n_targets`` (first insertion away from ``avoid``), polished."""
        state = FitState.empty()
        if self._compiled_search(run) and n_targets > 0:
            state = self._grow_compiled(run, state, self._lm.inner_iter, avoid, n_targets)
        while state.n_targets < n_targets:
            first = state.n_targets == 0
            state = self._grow(run, state, self._lm.inner_iter, avoid if first else None)
        return self._polish(run, state)

    def _prescale(self, values: FloatArray, n_targets: int | None) -> float:
        """A first guess of the common power scale, when K is known and the received power
        per target is more than 1.5x outside what any grid point gives (brightest to
        faintest): the power per target over the room's mean. Else 1, and the search runs
        exactly as in a room measured as modelled (docs/explanation/solver.md, "Prescale")."""
        if n_targets is None:
            return 1.0
        upper, lower = self._upper_lower
        per_target = float(np.sum(values[upper == lower])) / n_targets
        low, high = self._energy_band
        if not np.isfinite(per_target) or low / 1.5 <= per_target <= 1.5 * high:
            return 1.0
        ratio = max(per_target, 1e-300) / self._mean_column_energy
        return float(np.clip(ratio, math.exp(-MAX_LOG_SCALE), math.exp(MAX_LOG_SCALE)))

    def _search(
        self, values: FloatArray, n_targets: int | None, prescale: float | None = None
    ) -> _Search:
        """The nominal fit of ``values`` (normalised units) with K counted or given, run at
        the common scale ``prescale`` (else guessed by :meth:`_prescale`)."""
        if prescale is None:
            prescale = self._prescale(values, n_targets)
        # The whole search runs on the measurement divided by the guessed scale.
        run = _Run(values=values / prescale, priors=self._growth_priors)
        # Local optima the search found but did not pick: the joint fit with the room's
        # tolerances, which can tell them apart better, tries them again.
        others: list[FloatArray] = []
        if n_targets is None:
            return _Search(run, self._polish(run, self._count_and_fit(run)), others, prescale)
        state = self._fit_known(run, n_targets, np.zeros((0, 2)))
        cost = self._plain_cost(run, state)
        firsts = [state.positions[0]]
        for _ in range(self._restarts if n_targets > 1 else 0):
            if not self._needs_escape(run, state):
                break
            other = self._fit_known(run, n_targets, np.array(firsts))
            firsts.append(other.positions[0])
            other_cost = self._plain_cost(run, other)
            if other_cost < cost:
                state, cost, other = other, other_cost, state
            others.append(other.positions)
        return _Search(run, state, others, prescale)

    def _scale_free_fit(self, values: FloatArray, search: _Search) -> tuple[float, float]:
        """The plain cost of a search's fit of ``values`` with its targets' atoms under
        their least-squares common scale (the noise term as fitted), and that scale: what
        the fit leaves whatever the measurement's scale, so fits run at different guessed
        scales compare."""
        run, state = search.run, search.state
        atom = self._identity.data(noise_atom(self.model, self.fingerprint.n_leds))
        noise = state.noise * atom
        signal = run.values - self._residual(run, self._identity, state) - noise
        data = values - search.prescale * noise
        energy = float(signal @ signal)
        scale = float(data @ signal) / energy if energy > 0.0 else 0.0
        rest = data - scale * signal
        return float(rest @ rest), scale

    def _search_at_scale(self, values: FloatArray, n_targets: int) -> tuple[_Search, float]:
        """:meth:`_search` with K given (read off the rank) and its fit's cost at its
        least-squares scale (:meth:`_scale_free_fit`). When that scale is more than
        ``rescale_search`` off the one the search ran at, searched again at it, and the fit
        that leaves less is kept. Unit-weight atoms under a scale error of 10-20 % misplace
        targets (the insertions and the first refinements run before the scale is fitted),
        and such a fit may not show that the count by energy left targets out; the data
        show the scale once positions are roughly right. (With K given by the client it was
        measured mixed, so it is not used there: docs/decisions/count-by-rank.md
        of R".)"""
        first = self._search(values, n_targets)
        cost, scale = self._scale_free_fit(values, first)
        tolerance = self.options.rescale_search
        if tolerance is None or not (
            scale > 0.0 and abs(math.log(scale / first.prescale)) > math.log1p(tolerance)
        ):
            return first, cost
        second = self._search(values, n_targets, scale)
        second_cost, _ = self._scale_free_fit(values, second)
        return (second, second_cost) if second_cost < cost else (first, cost)

    @staticmethod
    def _explains_more(n_values: int, cost: float, more_cost: float, extra: int) -> bool:
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

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values / self._scale**2
        search = self._search(values, n_targets)
        if n_targets is None and self.options.count_by_rank:
            # A sum of K terminals' outer products has rank K, whatever the scale. A count
            # above it is wrong; one below it is either a low scale (the energy rule counts
            # in units of the fingerprint's) or terminals that saw no LED (noise only): the
            # rank's fit is taken when it leaves far less, at the scale the data show.
            counted = search.state.n_targets
            summed = summed_terminals(measurement)
            if summed is not None and summed <= self._max_count and summed != counted:
                known, known_cost = self._search_at_scale(values, summed)
                if summed < counted or self._explains_more(
                    values.shape[0],
                    self._scale_free_fit(values, search)[0],
                    known_cost,
                    summed - counted,
                ):
                    search = known
        run, state, others, prescale = search
        state = self._with_nuisances(run, state)
        tolerances = self._with_room_tolerances(run, state, tuple(others))
        if tolerances is not None:
            state = tolerances.state
        residual = self._residual(run, self._identity, state)
        if tolerances is None:
            covariances, fit = self._uncertainty(run, state)
        else:
            # The joint fit's own information: its model holds what the nominal one misses.
            covariances = tolerances.covariances
            fit = assess_fit(tolerances.chi2, tolerances.dof, math.exp(0.5 * state.log_scale))
        # The layout's tilt spread widens the radii by what its tilts move the estimates,
        # unless the joint fit fitted them (its covariances then hold them).
        tilted = (
            self._tilt_covariances(run, state)
            if tolerances is None or tolerances.tilts is None
            else None
        )
        if tilted is not None:
            covariances = covariances + tilted
        far = self._aggregated_far_optima(run, state, covariances)
        if prescale != 1.0:
            state.log_scale += math.log(prescale)
            state.facts = None
            fit = assess_fit(
                fit.chi2_per_dof * max(fit.dof, 1), fit.dof, math.exp(0.5 * state.log_scale)
            )
        if tolerances is not None:
            amplitude_rms = float(np.sqrt(np.mean(np.expm1(tolerances.led_log_amplitudes) ** 2)))
            angle_rms = float(np.sqrt(np.mean(tolerances.led_half_power_changes_deg**2)))
            tilts = (
                ""
                if tolerances.tilts is None
                else ", and the photodiodes' tilts "
                f"({math.degrees(float(np.sqrt(np.mean(tolerances.tilts**2)))):.1f} deg rms "
                "per component)"
            )
            fit = replace(
                fit,
                detail=f"{fit.detail}; the LEDs' tolerances were fitted (amplitudes "
                f"{100 * amplitude_rms:.1f} % and half-power angles {angle_rms:.1f} deg rms "
                f"from the layout){tilts}: a survey calibration would measure the LEDs once",
            )
        if not self._noise_identified and fit.quality != "scale_mismatch":
            # No noise level to hold the residuals against: no goodness-of-fit test.
            fit = replace(fit, quality="ok", detail=_NO_FIT_TEST)
        unknowns = 2 * state.n_targets + 1
        if residual.shape[0] < unknowns and fit.quality != "scale_mismatch":
            fit = replace(
                fit,
                quality="poor",
                detail=f"{residual.shape[0]} values cannot determine {state.n_targets} targets "
                f"and the noise ({unknowns} unknowns): other placements fit them as well; "
                "send the correlation matrix or each terminal's amplitudes",
            )
        positions = state.positions
        covariances, fit = self._reported(positions, covariances, fit, far)
        return Solution(
            positions=positions,
            grid_indices=self.fingerprint.layout.nearest_cell(positions),
            weights=state.weights.copy(),
            noise_power=state.noise * prescale * self._scale**2,
            residual_norm=float(np.linalg.norm(residual)) * prescale * self._scale**2,
            n_iter=run.iterations,
            converged=state.converged,
            covariances=covariances,
            gains=np.exp(0.5 * state.log_scale + state.log_gains),
            heights=state.heights.copy() if self._priors.fits_heights else None,
            fit=fit,
        )

    def solve_terminals(
        self,
        amplitudes: FloatArray,
        heights: FloatArray | None = None,
        normals: FloatArray | None = None,
        floors: FloatArray | None = None,
    ) -> Solution:
        """Locate each terminal from its own amplitudes; estimate k belongs to terminal k.

        Parameters
        ----------
        amplitudes : ndarray of shape (K, M)
            Each terminal's received pilot amplitudes (validated by the caller); NaN where
            the LED was not detected (censored below the terminal's floor: :mod:`._censored`).
        heights : ndarray of shape (K,) or None, metres
            Terminals' own heights; NaN (or None for all) where unknown.
        normals : ndarray of shape (K, 3) or None
            Terminals' photodiode unit normals; None for straight up.
        floors : ndarray of shape (K,) or None
            Terminals' detection floors (amplitude units); NaN (or None for all): the
            weakest amplitude each detected.

        Notes
        -----
        See :mod:`.gridless.terminals`. Two passes: without priors, to estimate the amplitude
        noise variance pooled over the terminals (its residual sum of squares over its
        degrees of freedom), then with the gain and height priors weighted by it (each
        terminal's gain held at 1 and its photodiode level unless freeing them lowers the
        cost significantly, or its tilt fitted with the layout's ``receiver_tilt_sd`` as
        the prior when it declares one: :func:`.terminals.fit_terminal`). The covariance of
        each position is the sandwich of its whitened fit with the noise and
        the model errors the fit does not fit (:meth:`_terminal_misfit_columns`), their
        variances estimated from all terminals' residuals together (the first pass's noise
        level holds part of the misfit, so the noise variance is re-estimated with them)
        and widened for their degrees of freedom (:mod:`app.vlp.uncertainty`). When the
        LEDs' relative errors explain a significant share of the residuals
        (:func:`_led_errors_seen`; option ``terminal_led_weights``), a third pass refits each
        terminal with each amplitude's variance the noise's plus that error's, and the
        variances are estimated again from its residuals.
        """
        # [censored hook] LEDs not detected enter as their interval below the floor.
        amplitudes, censored_var = censored_substitutes(
            np.asarray(amplitudes, dtype=np.float64), floors
        )
        check_amplitude_scale(self.fingerprint, amplitudes)
        values = amplitudes / self._scale
        censored_var = censored_var / self._scale**2
        n_terminals, n_leds = values.shape
        windows = self._windows
        if windows is None:
            if self._dense:
                correlations = values @ self._gains
            else:
                correlations = np.asarray((self._gains_sparse.T @ values.T).T)
            scores = np.where(correlations > 0.0, correlations**2 / self._column_energy, 0.0)
        spacing = 2.0 * self.fingerprint.layout.grid.step
        own_heights = [
            None if heights is None or not np.isfinite(heights[k]) else float(heights[k])
            for k in range(n_terminals)
        ]
        own_normals = [None if normals is None else normals[k] for k in range(n_terminals)]
        # The layout's tilt spread, when it declares one, is each unknown tilt's prior; a
        # layout whose photodiodes are level has no tilt to fit.
        declared_tilt_sd = math.radians(self.fingerprint.layout.grid.receiver_tilt_sd)
        tilt_spread_known = self.options.tilt_sd is not None and declared_tilt_sd > 0
        tilt_sd = declared_tilt_sd if tilt_spread_known else self.options.tilt_sd
        if self._receivers_level:
            tilt_sd = None
        first = []
        for k in range(n_terminals):
            kernel, seen, unseen_energy = self._kernel, values[k], 0.0
            if windows is None:
                cells = starting_cells(scores[k], self._centres, spacing)
            else:
                # Large rooms: the first pass (starts and the noise estimate) fits the LEDs
                # near the terminal; the second pass below fits all of them.
                cells = windows.starting_cells(values[k], self._centres, spacing)
                kernel, inside = windows.near_kernel(values[k], self._scale)
                seen = values[k][inside]
                unseen_energy = float(values[k] @ values[k] - seen @ seen)
            fit = fit_terminal(
                kernel,
                seen,
                self._centres[cells],
                priors=self._priors,
                sigma2=None,
                height=own_heights[k],
                normal=own_normals[k],
                tilt_sd=tilt_sd,
                tilt_spread_known=tilt_spread_known,
            )
            first.append(replace(fit, rss=fit.rss + unseen_energy))
        dof = np.array([max(n_leds - fit.n_params, 1) for fit in first])
        sigma2 = sum(fit.rss for fit in first) / float(dof.sum())
        fits = [
            fit_terminal(
                self._kernel,
                values[k],
                first[k].position[None, :],
                priors=self._priors,
                sigma2=with_censored_variance(sigma2, censored_var[k]),  # [censored hook]
                height=own_heights[k],
                normal=own_normals[k],
                tilt_sd=tilt_sd,
                tilt_spread_known=tilt_spread_known,
            )
            for k in range(n_terminals)
        ]

        def misfit_of(
            fits: list[TerminalFit], led_errors: bool = True
        ) -> tuple[list[MisfitDesign], Misfit]:
            designs = [
                _misfit_design(
                    fit.jacobian,
                    fit.normal,
                    self._terminal_misfit_columns(
                        fit, own_heights[k] is not None, own_normals[k] is not None, led_errors
                    ),
                )
                for k, fit in enumerate(fits)
            ]
            return designs, fit_misfit(designs, [fit.residual for fit in fits])

        designs, misfit = misfit_of(fits)
        # The goodness of fit is the layout's own, with one weight for all amplitudes: the
        # reweighted fit below explains its residuals by construction.
        chi2 = np.array([fit.rss for fit in fits]) / max(sigma2, 1e-300)
        led_error = float(misfit.model_errors[0]) if misfit.model_errors.size else 0.0
        reweighted = self.options.terminal_led_weights and _led_errors_seen(designs, led_error)
        if reweighted:
            fits = [
                fit_terminal(
                    self._kernel,
                    values[k],
                    fit.position[None, :],
                    priors=self._priors,
                    sigma2=with_censored_variance(  # [censored hook]
                        misfit.noise * sigma2
                        + led_error * (fit.jacobian[:, -1] / fit.data_weight) ** 2,
                        censored_var[k],
                    ),
                    height=own_heights[k],
                    normal=own_normals[k],
                    tilt_sd=tilt_sd,
                    tilt_spread_known=tilt_spread_known,
                )
                for k, fit in enumerate(fits)
            ]
            # The LEDs' errors are in the weights now: a model error along them as well
            # would count them twice (radii too wide).
            designs, misfit = misfit_of(fits, led_errors=False)
        covariances = np.array(
            [
                predictive_covariances(design, misfit, np.array([[0, 1]]))[0]
                # A terminal whose own residual the pooled variances do not explain: its radius
                # says so (a terminal at a wrong optimum, or more impaired than the rest).
                * own_excess_widening(design, fit.residual, misfit)
                for design, fit in zip(designs, fits, strict=True)
            ]
        )
        if declared_tilt_sd > 0:
            for k, fit in enumerate(fits):
                if not (fit.free_tilt or own_normals[k] is not None):
                    covariances[k] += self._terminal_tilt_covariance(fit, declared_tilt_sd)
        log_gains = np.array([fit.log_gain for fit in fits])
        positions = np.array([fit.position for fit in fits])
        fit_quality = assess_fit(
            float(chi2.sum()), int(dof.sum()), math.exp(float(np.median(log_gains)))
        )
        if reweighted and fit_quality.quality != "scale_mismatch":
            seen = (
                f"the residuals grow with the amplitudes as if the LEDs were about "
                f"{100.0 * math.sqrt(led_error):.0f} % off their data sheet, and the brightest "
                "were weighted down for it (a survey calibration measures them)"
            )
            # The noise level was estimated from the same residuals: "to its noise" would
            # hide what they show.
            detail = (
                seen if fit_quality.detail == FITS_TO_NOISE else f"{fit_quality.detail}; {seen}"
            )
            fit_quality = replace(fit_quality, detail=detail)
        far = self._far_optima(values, positions, covariances, sigma2)
        covariances, fit_quality = self._reported(positions, covariances, fit_quality, far)
        return Solution(
            positions=positions,
            grid_indices=self.fingerprint.layout.nearest_cell(positions),
            weights=np.ones(n_terminals),
            noise_power=n_terminals * sigma2 * self._scale**2,
            residual_norm=math.sqrt(sum(fit.rss for fit in fits)) * self._scale,
            n_iter=len(fits),
            converged=True,
            covariances=covariances,
            gains=np.exp(log_gains),
            heights=np.array([fit.height for fit in fits])
            if self._priors.fits_heights or heights is not None
            else None,
            fit=fit_quality,
        )

    def _terminal_tilt_covariance(self, fit: TerminalFit, tilt_sd: float) -> FloatArray:
        """A terminal's position covariance from a photodiode tilt of the layout's spread
        that its fit holds level, shape (2, 2): as :meth:`_tilt_covariances`, with the
        terminal's own whitened Jacobian (position first)."""
        gradient = self._shape_gradients(fit.position[np.newaxis, :], np.array([fit.height]))[0]
        weight = np.reshape(fit.data_weight, (-1, 1))
        columns = weight * math.exp(fit.log_gain) * gradient[:, 1:3]  # (M, 2)
        position = np.array([[0, 1]])
        covariances = _response_covariances(fit.normal, fit.jacobian.T, columns, position, tilt_sd)
        return np.asarray(covariances[0])

    def _terminal_misfit_columns(
        self, fit: TerminalFit, height_known: bool, normal_known: bool, led_errors: bool = True
    ) -> list[FloatArray]:
        """Whitened derivatives of a terminal's amplitudes along the errors its fit does not
        fit, as :meth:`_misfit_columns`: each LED's relative error, (M, M), then the
        photodiode's tilt, (M, 2), and its height, (M, 1), unless fitted or sent by the
        terminal (or, for the tilt, the layout's photodiodes are level), or for the LEDs'
        errors ``led_errors`` False (their variance already in the fit's weights) (then
        (M, 0): every terminal keeps the same components)."""
        whitened = fit.jacobian[:, -1]  # the log gain's column: the whitened amplitudes
        # LEDs out of view give zero columns: left out (a large room has hundreds).
        seen = (whitened != 0.0) & led_errors
        columns = [np.diag(whitened)[:, seen]]
        gradient = self._shape_gradients(fit.position[np.newaxis, :], np.array([fit.height]))[0]
        scale = np.reshape(fit.data_weight, (-1, 1)) * math.exp(fit.log_gain)
        unknown_tilt = not (fit.free_tilt or normal_known or self._receivers_level)
        unknown_height = not (fit.free_height or height_known)
        columns.append(scale * gradient[:, 1:3] if unknown_tilt else gradient[:, :0])
        columns.append(scale * gradient[:, 0:1] if unknown_height else gradient[:, :0])
        return columns

    def _with_nuisances(self, run: _Run, fixed: FitState) -> FitState:
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
        free_weights = self.options.free_weights
        white = self._whitening(best)
        # The freest stage is tested first: when even it promises nothing, neither does any
        # stage in between (one evaluation in the common case of a room as modelled).
        for index, priors in enumerate([self._stages[-1], *self._stages] if self._stages else []):
            run.priors = priors
            slots = _Slots.make(k, priors, free_weights)
            extra = slots.size - _Slots.make(k, kept, free_weights).size
            significant = extra + self.options.stage_significance * math.sqrt(2.0 * extra)
            objective = self._objective(run, white)
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
            if index == 0 and len(self._stages) > 1:
                continue  # promising: now stage by stage, the cheapest first
            freed = self._polish(run, best)
            if before - objective.cost(freed)[0] > significant:
                best, kept = freed, priors
                white = self._whitening(best)
        run.priors = kept
        return best

    def _with_room_tolerances(
        self, run: _Run, state: FitState, others: tuple[FloatArray, ...] = ()
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
        and last each photodiode's tilt (:meth:`_tolerance_tilt_sd`).

        Correlation model, K >= 2 (one target's LED errors cannot be told from its
        position), fixed unit weights and rooms whose Jacobian stays small (dense rooms).
        """
        opts = self.options
        k = state.n_targets
        n_leds = self.fingerprint.n_leds
        gain_sd, scale_sd = opts.log_gain_sd, opts.log_scale_sd
        if (
            self.model != "correlation"
            or opts.led_log_amplitude_sd is None
            or gain_sd is None
            or scale_sd is None
            or opts.free_weights
            or k < 2
            or not self._dense
            or run.values.shape[0] * (5 * k + 2 * n_leds + 2) > _MAX_MISFIT_ENTRIES
        ):
            return None
        white = self._whitening(state)
        data_cost = self._objective(run, white).data_cost(state)[0]
        dof = white.weights.shape[0] - 3 * k - 2
        if dof <= 0 or data_cost <= opts.tolerance_misfit_ratio * dof:
            return None  # the fit leaves only noise: nothing for the tolerances to explain
        tolerances = RoomTolerances(
            opts.led_log_amplitude_sd, opts.led_half_power_sd_deg, opts.room_tilt_sd
        )
        return fit_room_tolerances(
            self._kernel,
            run.values,
            state,
            (gain_sd, scale_sd),
            tolerances,
            opts.tolerance_significance,
            GridMoves(
                self._gains,
                self._centres,
                self._avoid_radius,
                self._priors.height_mean,
                others,
                0.5 * self.fingerprint.layout.grid.step,
            )
            if opts.tolerance_jumps
            else None,
            opts.tolerance_score_ratio,
            self._tolerance_tilt_sd(),
        )

    def _tolerance_tilt_sd(self) -> float:
        """The prior sd (per tangent component, about radians) of the photodiodes' tilts in
        the joint fit's last stage: the layout's spread, else the hand-held default
        (``tolerance_tilt_sd``); 0 where the layout's photodiodes are level or the stage is
        off."""
        opts = self.options
        if opts.tolerance_tilt_sd <= 0 or self._receivers_level:
            return 0.0
        declared = math.radians(self.fingerprint.layout.grid.receiver_tilt_sd)
        return declared if declared > 0 else opts.tolerance_tilt_sd

    def _uncertainty(self, run: _Run, state: FitState) -> tuple[FloatArray, FitQuality]:
        """Position covariances of the final whitened fit and the fit's quality
        (docs/explanation/solver.md, "Uncertainty").

        The inverse Fisher information alone counts only the noise; a room that differs
        from its model moves the estimates further. The covariance is the sandwich
        ``A (J^T J + sum_c b_c J^T F_c F_c^T J + N_prior) A`` over the model errors the fit
        does not fit (:meth:`_misfit_columns`), each variance ``b_c`` estimated from the
        residuals at the optimum net of what the fitted parameters absorbed
        (:func:`app.vlp.uncertainty.fit_misfit`), then widened for those estimates' few
        degrees of freedom (:func:`app.vlp.uncertainty.predictive_covariances`). The whitened
        noise variance is fitted with them, at most 1: the whitening's noise level comes
        from the fitted noise atom, which absorbs misfit on the diagonal of ``R`` (so a room
        off its model shows a reduced chi-square below 1, not above), never less than the
        noise. A room too large to hold the model-error design falls back to inflating the
        inverse Fisher information by the reduced chi-square when above 1.
        """
        return self._covariances(self._objective(run, self._whitening(state)), state)

    def _tilt_covariances(self, run: _Run, state: FitState) -> FloatArray | None:
        """Position covariances from unknown photodiode tilts of the layout's spread
        (``grid.receiver_tilt_sd``), shape (K, 2, 2); None without one.

        A tilt is nearly a shift of the position, so the residuals cannot show it (the
        model-error variances of :meth:`_misfit_columns` stay near 0), only the layout can.

        Each target's two tilt components (radians, independent, sd ``tilt_sd``) move its
        gains along their tilt derivatives (:meth:`_shape_gradients`), so the whitened model
        by ``F t`` (:meth:`_perturbation_columns`, (L, 2 K)); the fit then moves its
        parameters by ``G t`` with ``G = (J^T J)^+ J^T F`` (a small-perturbation, Gauss-Newton
        step), and the positions' covariance is ``tilt_sd^2 G_pos G_pos^T``. Rooms too large
        to hold the model-error design (as :meth:`_misfit_columns`) get None.
        """
        tilt_sd = math.radians(self.fingerprint.layout.grid.receiver_tilt_sd)
        k = state.n_targets
        n_data = run.values.shape[0]
        if tilt_sd == 0 or k == 0 or n_data * k * self.fingerprint.n_leds > _MAX_MISFIT_ENTRIES:
            return None
        objective = self._objective(run, self._whitening(state))
        theta = objective.pack(state)
        jacobian = objective.augmented(theta, state)[: theta.shape[0]]  # (P, L + n_prior)
        gains = target_gains(self._kernel, state)
        tilts = self._shape_gradients(state.positions, state.heights)[:, :, 1:]
        columns = self._perturbation_columns(objective, theta, state, gains, tilts)
        index = np.column_stack((np.arange(k), np.arange(k) + k))
        return _response_covariances(
            jacobian @ jacobian.T, jacobian[:, :n_data], columns, index, tilt_sd
        )

    def _far_optima(
        self, values: FloatArray, positions: FloatArray, covariances: FloatArray, sigma2: float
    ) -> FloatArray:
        """Each terminal's farthest other optimum of its own amplitudes beyond its radius
        (:func:`app.vlp.ambiguity.far_optima`: a grid point that explains them as well, e.g.
        a receiver in a dark corner, or on either side of a row of LEDs), shape (K, 2), NaN
        where none. Dense rooms whose gains are small enough to scan per answer (else all
        NaN)."""
        if not self._scans_profiles:
            return np.full_like(positions, np.nan)
        return far_optima(
            values,
            self._gains,
            self._centres,
            positions,
            covariances,
            sigma2,
            self.fingerprint.layout.grid.step,
            self._column_energy,
        )

    def _aggregated_far_optima(
        self, run: _Run, state: FitState, covariances: FloatArray
    ) -> FloatArray:
        """Each estimate's farthest other optimum of the aggregated measurement beyond its
        radius, shape (K, 2), NaN where none: the estimate moved over the grid with the
        others held, its gain free (:meth:`_profiles`), and the region where that profile
        is within chi-square(2)'s 95 % of its best
        (:func:`app.vlp.ambiguity.farthest_in_region`). It finds what the covariance, a
        curvature at one optimum, cannot: a receiver in the dark, the other side of a row of
        LEDs, a spot that another target's light also explains. Dense rooms whose gains are
        small enough to scan per answer (else all NaN)."""
        k = state.n_targets
        if not self._scans_profiles or k == 0:
            return np.full((k, 2), np.nan)
        explained, best = self._profiles(run, state)
        return farthest_in_region(
            explained,
            best,
            self._centres,
            state.positions,
            covariances,
            self.fingerprint.layout.grid.step,
        )

    def _profiles(self, run: _Run, state: FitState) -> tuple[FloatArray, FloatArray]:
        """How much of the whitened cost each estimate would explain at every grid point,
        the others held and its gain free, shape (K, N), and how much it explains where it
        is, shape (K,) (dense rooms, the final whitened metric).

        Without estimate k the whitened residual is ``r_k = r + w_k a_k`` (``a_k`` its
        whitened atom, ``w_k`` its effective weight); a unit atom ``a_j`` at grid point j
        with its gain free explains ``max(<a_j, r_k>, 0)^2 / ||a_j||^2``, and the estimate
        itself ``||r_k||^2 - ||r||^2``. In the rotated basis (``rho = U^T g``) every inner
        product of atoms is a quadratic form in ``rho_j o rho_k`` with the squared weights,
        so all K profiles cost one pass over the grid each, without forming any ``r_k``
        (compiled: :func:`.gridless._compiled.fit.correlation_profiles_kernel`, this NumPy code its
        reference). Kept per run, state values and priors.
        """
        key = (state_key(state), run.priors)
        known = run.profiles.get(key)
        if known is None:
            known = run.profiles[key] = self._profiles_of(run, state)
        return known

    def _profiles_of(self, run: _Run, state: FitState) -> tuple[FloatArray, FloatArray]:
        """:meth:`_profiles`, computed."""
        white, residual = self._whitened_residual(run, state)
        weights = white.weights
        n_leds = self.fingerprint.n_leds
        targets = target_gains(self._kernel, state)  # (M, K)
        multipliers = state.effective_weights()
        if self.model == "power":
            # The insertion scores' inner products (exact for power), and the cross terms.
            num, norms = self._correlations(white, residual)
            squared = weights**2
            target_sq = targets**2
            cross = (target_sq * squared[:, np.newaxis]).T @ self._gains_sq  # (K, N)
            without = num[np.newaxis, :] + multipliers[:, np.newaxis] * cross
            own_num = (weights * residual) @ target_sq
            own_norm = squared @ target_sq**2
        elif kernel_mode() == "compiled":
            without, norms, own_num, own_norm = correlation_profiles_kernel(
                white.compiled(),
                np.ascontiguousarray(residual, dtype=np.float64),
                self._gains,
                np.ascontiguousarray(targets, dtype=np.float64),
                np.ascontiguousarray(multipliers, dtype=np.float64),
            )
        else:
            # Symmetric M x M forms of the whitened entries (each off-diagonal entry split
            # over its two places): r's, and the squared weights'.
            quadratic = np.zeros((n_leds, n_leds))
            quadratic[white.upper, white.lower] = 0.5 * weights * residual
            quadratic = quadratic + quadratic.T
            squared = np.zeros((n_leds, n_leds))
            squared[white.upper, white.lower] = 0.5 * weights**2
            squared = squared + squared.T
            grid = white.rotate(self._gains)  # (M, N)
            rotated = white.rotate(targets)  # (M, K)
            # r_k's form: r's plus w_k times the squared weights on rho_k rho_k^T.
            forms = quadratic + multipliers[:, np.newaxis, np.newaxis] * squared * (
                rotated.T[:, :, np.newaxis] * rotated.T[:, np.newaxis, :]
            )
            without = np.sum(np.matmul(forms, grid) * grid, axis=1)  # (K, N)
            grid_sq = grid * grid
            norms = np.sum((squared @ grid_sq) * grid_sq, axis=0)
            own_num = np.sum((quadratic @ rotated) * rotated, axis=0)
            rotated_sq = rotated * rotated
            own_norm = np.sum((squared @ rotated_sq) * rotated_sq, axis=0)
        explained = np.maximum(without, 0.0) ** 2 / np.maximum(norms, 1e-300)
        own = 2.0 * multipliers * own_num + multipliers**2 * own_norm
        return explained, np.maximum(explained.max(axis=1), own)

    def _gains_at(self, points: FloatArray) -> FloatArray:
        """The channel gains (M, P) at ``points`` (P, 2) on the receivers' plane."""
        return self._kernel.gains_xy(points[:, 0], points[:, 1])

    def _reported(
        self,
        positions: FloatArray,
        covariances: FloatArray,
        fit: FitQuality,
        far: FloatArray,
    ) -> tuple[FloatArray, FitQuality]:
        """The covariances (K, 2, 2) and fit quality an answer reports: each estimate's
        region widened to hold its mirror twin (:mod:`app.vlp.ambiguity`: LEDs on one line
        give the same gains on both sides) or its ``far`` optimum (shape (K, 2), NaN where
        none; :meth:`_far_optima`, :meth:`_aggregated_far_optima`), the farther of the two,
        the fit's detail saying so, and no 95 % radius beyond the floor's diagonal
        (:func:`app.vlp.uncertainty.bounded_covariances`)."""
        room = self.fingerprint.layout.room
        twins = (
            mirror_twins(positions, self._led_xy, self._gains_at, (room.length, room.width))
            if self._twins_possible
            else np.full_like(positions, np.nan)
        )
        has_twin = np.isfinite(twins[:, 0])
        has_far = np.isfinite(far[:, 0])
        if has_far.any():
            # One widening per estimate, to the farther point: the far optimum when the
            # twin is nearer or none.
            to_twin = np.linalg.norm(twins - positions, axis=1)
            to_far = np.linalg.norm(far - positions, axis=1)
            has_far &= ~(has_twin & (to_twin > to_far))
            has_twin &= ~has_far
            twins = np.where(has_far[:, np.newaxis], far, twins)
        if has_twin.any() or has_far.any():
            covariances = covering_twins(covariances, positions, twins)
        detail = fit.detail
        if has_far.any():
            detail += (
                f"; {int(has_far.sum())} of the estimates would fit the measurement about "
                "as well at another place beyond their radius: their radii hold it"
            )
        if has_twin.any():
            detail += (
                f"; {int(has_twin.sum())} of the estimates see LEDs on one line and have a "
                "mirror image across it that receives the same signals: their radii hold both "
                "(LEDs off that line would tell them apart)"
            )
        if detail != fit.detail:
            fit = replace(fit, detail=detail)
        return bounded_covariances(covariances, math.hypot(room.length, room.width)), fit

    def _covariances(self, objective: Objective, state: FitState) -> tuple[FloatArray, FitQuality]:
        """:meth:`_uncertainty` in the metric of ``objective``: compiled
        (:mod:`.gridless._compiled.uncertainty`) or, with the reference kernels, in NumPy."""
        theta = objective.pack(state)
        k = state.n_targets
        index = np.column_stack((np.arange(k), np.arange(k) + k))
        n_params, n_data = theta.shape[0], objective.data.shape[0]
        scale = math.exp(0.5 * state.log_scale)
        problem = objective.compiled_problem()
        small = n_data * k * self.fingerprint.n_leds <= _MAX_MISFIT_ENTRIES
        if problem is not None and k > 0 and small:
            # The same sandwich in one compiled call (.gridless._compiled.uncertainty).
            covariances, cost = uncertainty_kernel(
                *problem,
                theta,
                *objective.compiled_state(state),
                self._max_noise,
                self._receivers_level,
            )
            return covariances, assess_fit(float(cost), n_data - n_params, scale)
        columns = self._misfit_columns(objective, theta, state)
        if columns is None:
            normal, _, cost = gram(objective, theta, state)
            prior = objective.prior_residuals(theta, objective.slots(k))
            fit = assess_fit(cost - float(prior @ prior), n_data - n_params, scale)
            inverse = np.linalg.pinv(normal, hermitian=True) * max(1.0, fit.chi2_per_dof)
            return np.asarray(inverse[index[:, :, None], index[:, None, :]]), fit
        augmented = objective.augmented(theta, state)
        rows = augmented[:n_params]
        residual = augmented[n_params, :n_data]
        fit = assess_fit(float(residual @ residual), n_data - n_params, scale)
        design = misfit_design(rows[:, :n_data].T, rows @ rows.T, columns)
        misfit = fit_misfit([design], [residual], max_noise=self._max_noise)
        return predictive_covariances(design, misfit, index), fit

    def _misfit_columns(
        self, objective: Objective, theta: FloatArray, state: FitState
    ) -> list[FloatArray] | None:
        """Whitened derivatives of the model along the errors it does not fit: each target's
        relative amplitude error on each LED, shape (L, K M), and each target's photodiode
        tilt, shape (L, 2 K) (zeros where the layout's photodiodes are level); None when too
        large to hold (then the reduced chi-square inflates the inverse Fisher information
        instead).

        The room's residual model error (LEDs' power and beam tolerances, heights,
        reflections) scales with the signal: target k's amplitude from LED m is
        ``g_km (1 + d_km)``. A tilted photodiode moves its gains along their tilt
        derivatives, which the aggregated model does not fit. Each kind's variance is
        estimated from the residuals (:func:`app.vlp.uncertainty.fit_misfit`).
        """
        k, n_leds = state.n_targets, self.fingerprint.n_leds
        n_data = objective.data.shape[0]
        if n_data * k * n_leds > _MAX_MISFIT_ENTRIES:
            return None
        gains = target_gains(self._kernel, state)  # (M, K)
        relative = np.einsum("mk,mn->kmn", gains, np.eye(n_leds))  # diag(g_k) per target
        errors = self._perturbation_columns(objective, theta, state, gains, relative)
        tilts = self._shape_gradients(state.positions, state.heights)
        if self._receivers_level:
            tilts[:, :, 1:] = 0.0  # zero columns: no variance, as the compiled kernel
        out = [errors, self._perturbation_columns(objective, theta, state, gains, tilts[:, :, 1:])]
        if objective.slots(k).n_axes != 3:  # heights held fixed
            out.append(self._perturbation_columns(objective, theta, state, gains, tilts[:, :, :1]))
        return out

    def _shape_gradients(self, positions: FloatArray, heights: FloatArray) -> FloatArray:
        """Derivatives of each point's gains with respect to its height and its photodiode's
        tilt (tangent components, at level), shape (K, M, 3): ``[dg/dz, dg/dtx, dg/dty]``.

        Tilting the normal ``n`` moves the line of sight ``h ∝ n . v`` by
        ``h / v_z (v_x, v_y)`` per unit of tilt (``v`` = LED minus receiver); the diffuse
        part is modelled for a level photodiode (as in :func:`.gridless.terminals.terminal_model`).
        """
        kernel = self._kernel
        k = positions.shape[0]
        xs = np.ascontiguousarray(positions[:, 0], dtype=np.float64)
        ys = np.ascontiguousarray(positions[:, 1], dtype=np.float64)
        zs = np.ascontiguousarray(heights, dtype=np.float64)
        constants = channel_constants(kernel) if kernel_mode() == "compiled" else None
        along_z: FloatArray
        if constants is not None:
            along_z = channel_rows(*constants, xs, ys, zs, False)[3]  # (K, M)
        else:
            along_z = kernel.gradients_xyz(xs, ys, zs)[:, 2 * k : 3 * k].T
        offsets = kernel.led_xyz[:, np.newaxis, :] - np.column_stack((positions, heights))
        drop = np.maximum(offsets[:, :, 2], 1e-9)  # (M, K)
        dist2 = np.einsum("mkc,mkc->mk", offsets, offsets)
        orders = kernel.orders[:, np.newaxis]
        los = (
            kernel.free_height_factor[:, np.newaxis]
            * drop ** (orders + 1.0)
            * dist2 ** (-(orders + 3.0) / 2.0)
            * (drop * drop >= kernel.cos_fov2 * dist2)
        )
        out = np.empty((k, kernel.n_leds, 3))
        out[:, :, 0] = along_z
        out[:, :, 1:] = ((los / drop)[:, :, np.newaxis] * offsets[:, :, :2]).transpose(1, 0, 2)
        return out

    def _perturbation_columns(
        self,
        objective: Objective,
        theta: FloatArray,
        state: FitState,
        gains: FloatArray,
        directions: FloatArray,
    ) -> FloatArray:
        """Whitened change of the model per unit of each target's gain perturbations.

        ``directions`` of shape (K, M, n): target k's gains move by ``directions[k] @ t``;
        in the aggregated correlation ``R`` moves by ``w_k (dg g_k^T + g_k dg^T)``.
        Returns shape (L, K n).
        """
        k, n_leds, n_dirs = directions.shape
        white = objective.white
        multipliers = objective._multipliers(theta, objective.slots(k), state)
        if multipliers is None:
            multipliers = np.ones(k)
        rotation = white.rotation if white.rotation is not None else np.eye(n_leds)
        rotated = (rotation.T @ gains)[:, :, np.newaxis]  # (M', K, 1)
        moved = np.einsum("ba,kbn->akn", rotation, directions)  # (M', K, n)
        if self.model == "power":
            block = 2.0 * moved * rotated
        else:
            upper, lower = white.upper, white.lower
            block = moved[upper] * rotated[lower] + rotated[upper] * moved[lower]
        block *= multipliers[np.newaxis, :, np.newaxis] * white.weights[:, np.newaxis, np.newaxis]
        return np.asarray(block.reshape(-1, k * n_dirs))


def _led_errors_seen(designs: list[MisfitDesign], led_error: float) -> bool:
    """Whether the LEDs' relative errors, variance ``led_error`` (the first model error of
    each design), explain more of the residuals' sum of squares than the noise's chi-square
    scatters (``_LED_WEIGHT_SIGNIFICANCE`` standard deviations): where the room's LEDs are
    as modelled, a moment estimate of ``led_error`` above 0 is the noise's chance; and
    whether it is an LED's error at all (relative sd at most ``_MAX_LED_ERROR_SD``)."""
    if not 0.0 < led_error <= _MAX_LED_ERROR_SD**2:
        return False
    seen = led_error * sum(float(design.error_leverages[:, 0].sum()) for design in designs)
    noise_dof = sum(float(design.noise_leverage.sum()) for design in designs)
    return seen > _LED_WEIGHT_SIGNIFICANCE * math.sqrt(2.0 * noise_dof)
