"""The frozen per-room precomputation of the default solver (:class:`PreparedRoom`;
docs/explanation/solver.md, "Room").

Everything that depends only on the fingerprint, the model and the options -- the channel
kernel, the grid's gains and their energies, the nuisance priors and stages, the resolved
``auto`` policies, the large rooms' scans and windows, the compiled search's constants -- is
computed once when the solver is built; solves only read it (solver objects are shared
between threads).
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from ...ambiguity import twins_possible
from ...fingerprints import Fingerprint
from ...measurements import Model
from ...simulation import mean_signal_power
from ...typing import FloatArray
from ..base import MAX_TARGETS
from ._compiled.channel import channel_constants
from .channel import ChannelKernel
from .local import PowerScan, TerminalWindows, squared_gains_dot
from .model import (
    Objective,
    _Slots,
)
from .options import (
    LM_DEFAULTS,
    GridlessOptions,
    LevenbergMarquardtSettings,
    diffuse_table,
    nuisance_priors,
    pick,
)
from .state import (
    FitState,
    Priors,
)
from .whitening import (
    Whitening,
    _vech_indices,
    compiled_indices,
)
from .whitening_memo import WhiteningMemo

# Largest model-error design (observations x targets x LEDs) held for the covariance; a
# larger room falls back to the reduced chi-square's inflation.
MAX_MISFIT_ENTRIES = 4_000_000
# Largest gains matrix (M x N entries) whose grid the far-optimum scans read per answer
# (gridless.report.terminal_far_optima and _aggregated_far_optima; K x M x N per answer, M^2 N per
# target for the correlation).
_MAX_PROFILE_ENTRIES = 1_000_000
# Grid steps added to the reach of a local refinement (targets move a little while fitted).
_NEAR_MARGIN_STEPS = 4.0


class PreparedRoom:
    """The default solver's per-room precomputation: built once per solver, read by every
    solve (attributes documented where they are set)."""

    def __init__(self, fingerprint: Fingerprint, model: Model, options: GridlessOptions) -> None:
        self.fingerprint = fingerprint
        self.model: Model = model
        self.options = options
        defaults = LM_DEFAULTS[model]
        self.lm = LevenbergMarquardtSettings(
            inner_iter=pick(self.options.inner_iter, defaults.inner_iter),
            initial_damping=pick(self.options.initial_damping, defaults.initial_damping),
            tol=pick(self.options.lm_tol, defaults.tol),
        )
        layout = fingerprint.layout
        self.scale = float(np.sqrt(mean_signal_power(fingerprint)))
        self.kernel = ChannelKernel(layout, self.scale, diffuse_table(fingerprint))
        # The power model has M values for 2K + 1 unknowns and a poorly identified noise
        # level (its noise atom is nearly a signal direction): its whitened statistics cannot
        # tell a freed nuisance from noise (an ideal room freed the scale in many K = 1 solves
        # and lost accuracy), so nuisances are fitted for correlation (and terminals).
        self.priors = nuisance_priors(
            layout,
            self.options if model == "correlation" else replace(self.options, log_gain_sd=None),
        )
        self.growth_priors = Priors(height_mean=self.priors.height_mean)
        # The covariance's noise variance, whitened: at most the whitening's own (1) where
        # the noise atom measures the noise (correlation: the diagonal of R); free for the
        # power model, whose noise atom (ones) is nearly a signal direction, so its fitted
        # noise level says nothing (0 in a third of ideal-room fits, several times the
        # truth in others) and only the residuals' scatter measures the noise.
        self.noise_identified = model == "correlation"
        self.max_noise = 1.0 if self.noise_identified else math.inf
        # Nuisances are freed in stages: the common scale and the heights, then the gains.
        full = self.priors
        scale_and_heights = replace(full, log_gain_sd=None)
        self.stages = [
            stage
            for stage in (scale_and_heights, full)
            if _Slots.make(1, stage, self.options.free_weights).size
            > _Slots.make(1, self.growth_priors, self.options.free_weights).size
        ]
        if len(self.stages) == 2 and self.stages[0] == self.stages[1]:
            self.stages.pop()
        # Whitenings already computed, by state values (.gridless.whitening_memo).
        self.whitenings = WhiteningMemo()
        self.centres = fingerprint.cell_centres()  # shared with the other model's room
        self.led_xy = np.ascontiguousarray(layout.led_positions[:, :2])
        self.dense = fingerprint.is_dense
        # Photodiodes the layout says face straight up: no tilt to fit or allow for.
        self.receivers_level = layout.grid.receivers_level
        # Most rooms have no mirror twins anywhere: their answers skip the check (decided
        # here, once, in dense rooms; large ones check every answer).
        floor = layout.room
        self.twins_possible = not self.dense or twins_possible(
            self.centres, self.led_xy, self.gains_at, (floor.length, floor.width)
        )
        self.relocate_to_missing = (
            not self.dense
            if self.options.relocate_to_missing is None
            else self.options.relocate_to_missing
        )
        self.relocate_far = (
            model == "power" and self.dense
            if self.options.relocate_far is None
            else self.options.relocate_far
        )
        self.grow_without_noise = (
            model == "power" and self.dense
            if self.options.grow_without_noise is None
            else self.options.grow_without_noise
        )
        self.restarts = pick(self.options.restarts, 0 if self.relocate_far else 1)
        # Restarts begin away from earlier first insertions, by half the mean LED height
        # above the receivers (about the size of one LED's bright spot).
        heights = layout.led_positions[:, 2] - layout.grid.receiver_height
        self.avoid_radius = 0.5 * float(np.mean(heights))
        n_obs = (
            fingerprint.n_leds
            if model == "power"
            else fingerprint.n_leds * (fingerprint.n_leds + 1) // 2
        )
        # Where the diagonal entries (each LED's received power) sit among the values.
        upper, lower, _ = _vech_indices(model, fingerprint.n_leds)
        self.diagonal = np.flatnonzero(upper == lower)
        # Each target costs 2 coordinates and the noise power one more unknown.
        self.max_count = max(1, min(MAX_TARGETS, fingerprint.n_cells, (n_obs - 1) // 2))
        # The far-place scans read every grid point per answer: dense rooms small enough.
        self.scans_profiles = (
            self.dense and fingerprint.n_leds * fingerprint.n_cells <= _MAX_PROFILE_ENTRIES
        )
        self.relocate_ambiguous = self.scans_profiles and (
            model == "correlation"
            if self.options.relocate_ambiguous is None
            else self.options.relocate_ambiguous
        )
        if self.dense:
            self.gains = np.ascontiguousarray(
                fingerprint.dense_scaled_gains() / self.scale, dtype=np.float64
            )
            self.gains_sq = self.gains**2
            self.gains_fourth = self.gains_sq**2
            self.column_energy = np.maximum(self.gains_sq.sum(axis=0), 1e-300)
        else:
            # Large rooms keep no scaled copy of G (nor of its square): their scans read
            # G^T, which the fingerprint holds once for both models (the correlation
            # operator's, also the windows' and the power scan's), and G / scale is made
            # only where a room without windows scores terminals (:attr:`gains_sparse`).
            self.operator = fingerprint.correlation_operator()
            self.gains_by_cell = self.operator.gains_by_cell
            total, fourth = _column_power_sums(fingerprint.scaled_gains(), 1.0 / self.scale)
            if model == "power":  # its scans' plain-metric norms; the power scan's too
                self.fourth_sums = fourth
            else:
                self.psi_norms = np.sqrt(0.5 * (total**2 + fourth))
            self.column_energy = np.maximum(total, 1e-300)
        self.mean_column_energy = float(np.mean(self.column_energy))
        # Large rooms: terminals are started near their own footprint (see ._local), as wide
        # as on the floor (a terminal may send its own height, down to 0).
        self.windows = None if self.dense else TerminalWindows.build(fingerprint, 0.0)
        if self.windows is not None and not self.windows.is_useful():
            self.windows = None
        # Large rooms (the terminals' rule: windows much smaller than the room), power model:
        # a refinement after an insertion or a relocation moves only the targets that can
        # share an LED with the changed ones (see :func:`.fitting.lm_fit_near`). Two
        # receivers on the plane share an LED only within twice the footprint radius of each
        # other.
        self.near_reach: float | None = None
        if self.windows is not None and model == "power":
            drop = float(layout.led_positions[:, 2].max()) - layout.grid.receiver_height
            radius = drop * math.tan(math.radians(layout.receiver.fov_deg))
            self.near_reach = 2.0 * radius + _NEAR_MARGIN_STEPS * layout.grid.step
        # Large rooms, power model: insertion scans score only the tiles that can hold the
        # best point (see ._local.PowerScan; the same argmax as scoring all N).
        self.power_scan = (
            PowerScan.build(fingerprint, self.scale, self.fourth_sums)
            if not self.dense and model == "power" and not self.options.free_weights
            else None
        )
        # The search's growth and refinement steps as one compiled call each
        # (:func:`.search.grow_kernel`, :func:`.search.refine_kernel`): their constants
        # (the channel's, the search priors' tuples, the entries' diagonal indicator), and
        # their bounds per noise ceiling and K.
        self.search_constants: tuple[Any, ...] | None = None
        self.search_objectives: dict[float, Objective] = {}
        constants = channel_constants(self.kernel)
        if (
            model == "correlation"
            and self.dense
            and self.near_reach is None
            and not self.options.free_weights
            and constants is not None
        ):
            search = self.search_objective(math.inf)
            one = FitState.empty().with_target(np.zeros(2), self.growth_priors.height_mean)
            _, search_layout, search_priors = search.compiled_state(one)
            _, _, is_diag = compiled_indices(model, fingerprint.n_leds)
            self.search_constants = (*constants, search_layout, search_priors, is_diag)
        # The faintest (5th percentile: corners out of view aside) and brightest grid points.
        self.energy_band = (
            float(np.percentile(self.column_energy, 5.0)),
            float(np.max(self.column_energy)),
        )

    @functools.cached_property
    def identity(self) -> Whitening:
        """Plain least squares, made on first use (a correlation model of the million-point
        hall's 1024 LEDs holds 20 MB in it, and its terminals' solves never read it); one
        object, whose compiled form the kernels keep."""
        return Whitening.identity(self.model, self.fingerprint.n_leds)

    @functools.cached_property
    def gains_sparse(self) -> sp.csr_array:
        """``G / scale`` of a large room, sparse (M, N): made on first use (only a room
        without terminal windows scores terminals with it)."""
        return sp.csr_array(self.fingerprint.scaled_gains() / self.scale)

    def squared_gains_dot(self, vector: FloatArray, fourth: bool = False) -> FloatArray:
        """``((G / scale)^2)^T @ vector`` (``fourth``: ``((G / scale)^4)^T @ vector``) of a
        large room, shape (N,), read from G^T (:func:`.local.squared_gains_dot`)."""
        return squared_gains_dot(self.gains_by_cell, 1.0 / self.scale, vector, fourth)

    def gains_at(self, points: FloatArray) -> FloatArray:
        """The channel gains (M, P) at ``points`` (P, 2) on the receivers' plane."""
        return self.kernel.gains_xy(points[:, 0], points[:, 1])

    def search_objective(self, ceiling: float) -> Objective:
        """An objective of the search priors with the noise at most ``ceiling``, for its
        parameter layout and bounds (its data are never read)."""
        found = self.search_objectives.get(ceiling)
        if found is None:
            found = self.search_objectives[ceiling] = Objective(
                self.kernel,
                self.identity,
                np.zeros(self.identity.weights.shape[0]),
                self.options.free_weights,
                self.growth_priors,
                ceiling,
            )
        return found


def _column_power_sums(gains: sp.csr_array, inverse_scale: float) -> tuple[FloatArray, FloatArray]:
    """``sum_i (g_ij / scale)^2`` and ``sum_i (g_ij / scale)^4`` of every column j of a CSR
    ``gains``, shapes (N,): the numbers ``(G / scale).power(n).sum(axis=0)`` computes (each
    column's entries added in row order, with the same powers), without its copies of G."""
    scaled = gains.data * inverse_scale
    n_cells = gains.shape[1]
    total = np.bincount(gains.indices, weights=scaled**2, minlength=n_cells)
    fourth = np.bincount(gains.indices, weights=scaled**4, minlength=n_cells)
    return np.asarray(total, dtype=np.float64), np.asarray(fourth, dtype=np.float64)
