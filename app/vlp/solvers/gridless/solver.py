"""The default solver: gridless (off-grid) localization by alternating descent conditional gradient.

ADCG (Boyd, Schiebinger and Recht, "The alternating descent conditional gradient method for
sparse inverse problems", SIAM J. Optim. 2017) applied to the aggregated VLP model.

:class:`GridlessSolver` is a thin estimator: it prepares the room once (:class:`.room.PreparedRoom`)
and its ``_solve`` runs the stages in order, each a module-level function of the package
(``docs/explanation/solver.md`` names the sections):

- :mod:`.search`: the nominal search (insertions, refinements, escapes, counting, prescale);
- :mod:`.stages`: the nuisance stages (scale and heights, gains, the room's tolerances);
- :mod:`.uncertainty`: the covariances of the positions;
- :mod:`.report`: far optima, mirror twins, bounded radii and every sentence of ``fit.detail``;
- :mod:`.terminal_solve`: terminals that send their own amplitudes.

:mod:`.fitting` holds what every stage calls (the run's objectives, whitenings and fits).
"""

from __future__ import annotations

import math

import numpy as np

from ...fingerprints import Fingerprint
from ...measurements import Measurement, Model
from ...radii import confidence_radii
from ...typing import FloatArray
from ..base import Solution, Solver, register_solver, with_radii
from .fitting import residual_of
from .options import LM_DEFAULTS, GridlessOptions
from .report import aggregated_far_optima, aggregated_fit_detail, reported
from .room import PreparedRoom
from .search import counted_search
from .stages import with_nuisances, with_room_tolerances
from .terminal_solve import solve_terminals
from .uncertainty import answer_uncertainty, rescaled_fit

__all__ = ["LM_DEFAULTS", "GridlessOptions", "GridlessSolver"]


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
    4. Escapes, only when the fit looks stuck (:func:`.search.needs_escape`): one pass of
       *relocation* moves (in large rooms also to where a target is missing), then, with
       K known and K > 1, ``restarts`` more runs whose first insertion avoids the earlier
       ones'; the lowest plain cost wins. The power model in small rooms relocates far
       instead, always from K = 2 (``relocate_far``: its fitted noise level hides a stuck
       fit), with no restarts.
    5. Nuisances in stages (:func:`.stages.with_nuisances`): the common scale and the heights
       (when ``grid.receiver_height_sd`` > 0), then each target's gain, each with a
       Gaussian prior (:class:`GridlessOptions`), kept only when a score test and then the
       fit show a decrease beyond the chance level of their extra parameters. Free
       weights instead of priors let a close pair merge into one target of weight 2.
       Then, for the correlation model at K >= 2, the LEDs' tolerances (each LED's
       amplitude and beam width, with data-sheet priors) in a joint fit, kept on the same
       kind of test when the fit shows a misfit (:func:`.stages.with_room_tolerances`).
       The joint fit then tries long moves of each target and the restarts' placements, and keeps
       those that lower its cost: it tells apart optima the nominal model cannot.
    6. Uncertainty (:func:`.uncertainty.fit_uncertainty`): the sandwich covariance of the final
       whitened fit with the noise and the model errors it does not fit (each target's relative
       amplitude error per LED, its photodiode's tilt, its height when not fitted), whose
       variances are estimated from the residuals net of what the fit absorbed and widened for
       their degrees of freedom (:mod:`app.vlp.uncertainty`); and the fit's quality
       (:func:`app.vlp.uncertainty.assess_fit`). Each radius also holds what a curvature cannot
       see: another place where the estimate, the others held, fits about as well
       (:func:`.report.aggregated_far_optima`), or its mirror image across a line of LEDs
       (:func:`.report.reported`).

    With K known the measurement is first divided by a guessed common scale when its power
    per target is more than 1.5x off the room's mean (:func:`.search.guessed_prescale`).
    Unknown K: first read off the correlation matrix's rank (``count_by_rank``,
    :func:`app.vlp.measurements.summed_terminals`): ``R = sum_k a_k a_k^T`` over K < M
    terminals has rank K exactly. Where the spectrum does not say (the power model, a matrix
    that is no such sum), targets are added one at a time; a state with more targets is
    kept when its plain cost is below the best so far by ``count_threshold`` times the
    energy ``||phi(p)||^2`` of the targets it adds, trying up to ``count_lookahead`` more
    before stopping. Terminals that send
    their own amplitudes are fitted one by one (:func:`.terminal_solve.solve_terminals`).

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
        # Everything that depends on the room and the options only, computed once.
        self.room = PreparedRoom(fingerprint, model, self.options)

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        """The stages in order (docs/explanation/solver.md): search, nuisances, the room's
        tolerances, uncertainty, far optima, the answer's report."""
        room = self.room
        values = measurement.values / room.scale**2
        # "Search" and "Counting": the nominal fit, K given, counted or read off the rank.
        run, state, others, prescale = counted_search(room, measurement, values, n_targets)
        # "Nuisance stages": the common scale and heights, then the gains, each gated.
        state = with_nuisances(room, run, state)
        # "Room tolerances": the LEDs' amplitudes and beams, where the fit shows a misfit.
        tolerances = with_room_tolerances(room, run, state, tuple(others))
        if tolerances is not None:
            state = tolerances.state
        residual = residual_of(room, run, room.identity, state)
        # "Uncertainty": the sandwich covariance (or the joint fit's own), with the tilts.
        covariances, fit = answer_uncertainty(room, run, state, tolerances)
        # "Far optima": where each estimate would fit about as well beyond its radius.
        far = aggregated_far_optima(room, run, state, covariances)
        if prescale != 1.0:
            # The search ran on the measurement divided by its guessed scale.
            state.log_scale += math.log(prescale)
            state.facts = None
            fit = rescaled_fit(fit, state.log_scale)
        # "Report": the fit's sentences, the twins and far optima in the radii.
        fit = aggregated_fit_detail(room, fit, tolerances, residual.shape[0], state.n_targets)
        positions = state.positions
        covariances, fit = reported(room, positions, covariances, fit, far)
        # The radii given here, not added by Solver.solve: no second Solution to build.
        return Solution(
            positions=positions,
            grid_indices=self.fingerprint.layout.nearest_cell(positions),
            weights=state.weights.copy(),
            noise_power=state.noise * prescale * room.scale**2,
            residual_norm=math.sqrt(float(residual @ residual)) * prescale * room.scale**2,
            n_iter=run.iterations,
            converged=state.converged,
            covariances=covariances,
            radii=confidence_radii(covariances),
            gains=np.exp(0.5 * state.log_scale + state.log_gains),
            heights=state.heights.copy() if room.priors.fits_heights else None,
            fit=fit,
        )

    def solve_terminals(
        self,
        amplitudes: FloatArray,
        heights: FloatArray | None = None,
        normals: FloatArray | None = None,
        floors: FloatArray | None = None,
    ) -> Solution:
        """Locate each terminal from its own amplitudes; estimate k belongs to terminal k
        (:func:`.terminal_solve.solve_terminals`, which documents the parameters)."""
        return with_radii(solve_terminals(self.room, amplitudes, heights, normals, floors))
