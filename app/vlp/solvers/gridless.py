"""The default solver: gridless (off-grid) localization by alternating descent conditional gradient.

ADCG (Boyd, Schiebinger and Recht, "The alternating descent conditional gradient method for
sparse inverse problems", SIAM J. Optim. 2017) applied to the aggregated VLP model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._typing import FloatArray
from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
from ..simulation import mean_signal_power
from ._gridless_fit import (
    ChannelKernel,
    FitState,
    Whitening,
    levenberg_marquardt,
    residual_and_jacobian,
)
from .base import MAX_TARGETS, Solution, Solver, register_solver

__all__ = ["GridlessSolver"]


@dataclass(frozen=True)
class GridlessOptions:
    """Tuning knobs (defaults are the measured best; see the solver's Notes)."""

    free_weights: bool = False
    whiten: bool = True
    inner_iter: int = 4
    final_iter: int = 50
    whiten_rounds: int = 3
    count_threshold: float = 0.2
    count_lookahead: int = 2
    relocate: bool = True


@register_solver
class GridlessSolver(Solver):
    """ADCG: insert at the best-correlated grid point, refine everything by LM, repeat.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}
    options : GridlessOptions, default=None
    """

    name = "gridless"
    description = "off-grid ADCG with whitened Levenberg-Marquardt refinement (default)"

    def __init__(self, fingerprint: Fingerprint, model: Model,
                 options: GridlessOptions | None = None) -> None:
        super().__init__(fingerprint, model)
        self.options = options or GridlessOptions()
        layout = fingerprint.layout
        self._scale = float(np.sqrt(mean_signal_power(fingerprint)))
        self._kernel = ChannelKernel(layout, self._scale)
        self._centres = layout.cell_centres()
        self._dense = fingerprint.is_dense
        n_obs = fingerprint.n_leds if model == "power" else \
            fingerprint.n_leds * (fingerprint.n_leds + 1) // 2
        # Each target costs 2 coordinates and the noise power one more unknown.
        self._max_count = max(1, min(MAX_TARGETS, fingerprint.n_cells, (n_obs - 1) // 2))
        if self._dense:
            self._gains = fingerprint.dense_scaled_gains() / self._scale
        else:
            self._gains_sparse = fingerprint.scaled_gains() / self._scale
            self._operator = fingerprint.correlation_operator()
            total = np.asarray(self._gains_sparse.power(2).sum(axis=0)).ravel()
            fourth = np.asarray(self._gains_sparse.power(4).sum(axis=0)).ravel()
            self._psi_norms = np.sqrt(0.5 * (total**2 + fourth))

    # -- insertion ---------------------------------------------------------------------
    def _scores(self, white: Whitening, residual: FloatArray) -> FloatArray:
        """Decrease of the whitened cost if a unit-weight target were added at each grid point.

        ``2 <c psi_j, r> - ||c psi_j||^2`` for fixed unit weights; the normalised correlation
        ``<c psi_j, r> / ||c psi_j||`` for free weights.
        """
        n_leds = self.fingerprint.n_leds
        weighted = white.weights * residual
        if self.model == "power":
            if self._dense:
                g2 = self._gains**2
                num = weighted @ g2
                norms = (white.weights**2) @ g2**2
            else:
                g2 = self._gains_sparse.power(2)
                num = g2.T @ weighted
                norms = g2.power(2).T @ white.weights**2
            return self._combine(num, norms)
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
            c2 = 0.5 * (c2 + c2.T) + 0.5 * np.diag(np.diag(c2))
            sq = rot**2
            norms = np.einsum("mj,mj->j", sq, c2 @ sq)
        else:
            # The operator's adjoint halves off-diagonal entries: pass 2 Q_il above the diagonal.
            upper, lower = np.triu_indices(n_leds)
            vech_q = np.where(upper == lower, 1.0, 2.0) * sym[upper, lower]
            num = self._operator.rmatvec(vech_q) / self._scale**2
            norms = self._psi_norms**2
        return self._combine(num, norms)

    def _combine(self, num: FloatArray, norms_sq: FloatArray) -> FloatArray:
        if self.options.free_weights:
            return np.asarray(num / np.sqrt(np.maximum(norms_sq, 1e-300)))
        return np.asarray(2.0 * num - norms_sq)

    # -- main loop -----------------------------------------------------------------------
    def _whitening(self, state: FitState) -> Whitening:
        if not self.options.whiten or state.positions.shape[0] == 0 or state.noise <= 0:
            return Whitening.identity(self.model, self.fingerprint.n_leds)
        return Whitening.from_state(self.model, self._kernel, state,
                                    float(state.positions.shape[0]))

    def _refine(self, values: FloatArray, state: FitState, max_iter: int,
                rounds: int) -> tuple[FitState, float, int]:
        total = 0
        cost = 0.0
        for _ in range(max(rounds, 1)):
            white = self._whitening(state)
            data = white.data(values, self.fingerprint.n_leds)
            state, cost, used = levenberg_marquardt(
                self._kernel, white, data, state, free_weights=self.options.free_weights,
                max_iter=max_iter)
            total += used
        return state, cost, total

    def _insert(self, values: FloatArray, state: FitState) -> FitState:
        # Large rooms score with the plain residual: whitened atom norms would need the
        # rotated gains of every grid point.
        white = self._whitening(state) if self._dense else Whitening.identity(
            self.model, self.fingerprint.n_leds)
        data = white.data(values, self.fingerprint.n_leds)
        residual, _ = residual_and_jacobian(self._kernel, white, data, state,
                                            self.options.free_weights, want_jacobian=False)
        best = int(np.argmax(self._scores(white, residual)))
        return FitState(np.vstack([state.positions, self._centres[best]]),
                        np.append(state.weights, 1.0), state.noise)

    def _plain_cost(self, values: FloatArray, state: FitState) -> float:
        plain = Whitening.identity(self.model, self.fingerprint.n_leds)
        residual, _ = residual_and_jacobian(self._kernel, plain, values, state, False,
                                            want_jacobian=False)
        return float(residual @ residual)

    def _atom_energy(self, position: FloatArray) -> float:
        gains, _ = self._kernel.gains(position[None, :])
        g2 = gains[:, 0] ** 2
        if self.model == "power":
            return float(g2 @ g2)
        return float(0.5 * (g2.sum() ** 2 + g2 @ g2))

    def _grow(self, values: FloatArray, state: FitState, max_iter: int) -> FitState:
        """One ADCG step: insert at the best grid point, then refine everything."""
        grown = self._insert(values, state)
        if max_iter > 0:
            grown, _, used = self._refine(values, grown, max_iter, 1)
            self._iterations += used
        return grown

    def _count_and_fit(self, values: FloatArray) -> FitState:
        """Grow one target at a time while each brings its own energy (unknown K).

        A real target removes about its own atom energy ``||phi(p)||^2`` from the plain
        residual; a spurious one, of unit weight, adds about as much. A state with more
        targets is kept when its cost is below the best so far by ``count_threshold`` times
        the energy of the targets it adds; up to ``count_lookahead`` more are tried before
        stopping (a close pair is often only resolved one target later).
        """
        opts = self.options
        state = FitState(np.zeros((0, 2)), np.zeros(0), 0.0)
        best, best_cost = state, self._plain_cost(values, state)
        while state.positions.shape[0] < self._max_count:
            state = self._grow(values, state, opts.inner_iter)
            state_cost = self._plain_cost(values, state)
            extra = state.positions.shape[0] - best.positions.shape[0]
            energy = sum(self._atom_energy(p) for p in state.positions[-extra:])
            if best_cost - state_cost >= opts.count_threshold * energy:
                best, best_cost = state, state_cost
            elif extra > opts.count_lookahead:
                break
        if best.positions.shape[0] == 0:
            best = self._insert(values, best)
        return best

    def _relocate(self, values: FloatArray, state: FitState) -> tuple[FitState, bool]:
        """ADCG's non-convex escape: move one target at a time to the best grid point of the
        residual left by the others, keep the move when the refined cost is lower."""
        moved = False
        step = self.fingerprint.layout.grid.step
        for k in range(state.positions.shape[0]):
            keep = np.arange(state.positions.shape[0]) != k
            others = FitState(state.positions[keep], state.weights[keep], state.noise)
            candidate = self._insert(values, others)
            if np.linalg.norm(candidate.positions[-1] - state.positions[k]) <= 1.5 * step:
                continue
            white = self._whitening(state)
            data = white.data(values, self.fingerprint.n_leds)
            current, _ = residual_and_jacobian(self._kernel, white, data, state, False,
                                               want_jacobian=False)
            candidate, cost, used = levenberg_marquardt(
                self._kernel, white, data, candidate,
                free_weights=self.options.free_weights, max_iter=self.options.final_iter)
            self._iterations += used
            if cost < float(current @ current):
                # Keep the original order: the moved target takes slot k.
                order = np.insert(np.arange(state.positions.shape[0] - 1), k,
                                  state.positions.shape[0] - 1)
                state = FitState(candidate.positions[order], candidate.weights[order],
                                 candidate.noise)
                moved = True
        return state, moved

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values / self._scale**2
        opts = self.options
        self._iterations = 0
        if n_targets is None:
            state = self._count_and_fit(values)
        else:
            state = FitState(np.zeros((0, 2)), np.zeros(0), 0.0)
            while state.positions.shape[0] < n_targets:
                state = self._grow(values, state, opts.inner_iter)
        state, _, used = self._refine(values, state, opts.final_iter, opts.whiten_rounds)
        self._iterations += used
        if opts.relocate:
            state, moved = self._relocate(values, state)
            if moved:
                state, _, used = self._refine(values, state, opts.final_iter, 1)
                self._iterations += used
        n_iter = self._iterations
        positions = state.positions
        plain = Whitening.identity(self.model, self.fingerprint.n_leds)
        residual, _ = residual_and_jacobian(self._kernel, plain, values, state, False,
                                            want_jacobian=False)
        return Solution(
            positions=positions,
            grid_indices=self.fingerprint.layout.nearest_cell(positions),
            weights=state.weights.copy(),
            noise_power=state.noise * self._scale**2,
            residual_norm=float(np.linalg.norm(residual)) * self._scale**2,
            n_iter=n_iter,
            converged=True,
        )
