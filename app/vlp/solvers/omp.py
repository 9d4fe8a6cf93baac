"""Orthogonal matching pursuit, the paper's greedy solver (section III)."""

from __future__ import annotations

import numpy as np

from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
from ..typing import FloatArray, IntArray
from ._counting import estimate_target_count
from ._grid import GridDictionary, fit_least_squares, grid_solution, nonnegative_fit
from .base import MAX_TARGETS, Solution, Solver, register_solver

__all__ = ["OmpSolver"]

# Columns whose part orthogonal to the noise atom is below this (relative) are never chosen.
_TINY = 1e-9


@register_solver
class OmpSolver(Solver):
    """OMP on the column-normalised ``J`` (power) or Psi (correlation) with a noise atom.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}

    Notes
    -----
    Each of K steps adds the grid column whose normalised atom has the largest absolute
    correlation with the current residual, then refits all chosen columns and the noise
    atom (``ones(M)`` or ``vech(I)``) by least squares; the noise coefficient is kept
    nonnegative and is reported as ``noise_power``, never as a target. This is the paper's
    OMP (Tropp and Gilbert 2007) applied to eqs. (12) and (16), with the noise atom chosen
    before the first step: residuals are then orthogonal to it, so each atom's correlation
    is divided by the norm of its part orthogonal to the noise atom (without this, a single
    target in the power model is found only about a quarter of the time).

    The dictionaries are very coherent (normalised columns 2 m apart still correlate
    ~0.4-0.5), so, faithful to the paper, OMP often misplaces targets when K >= 2 even
    without noise; ``nnls`` and ``l1`` do not. With ``n_targets=None`` K
    comes from :func:`~app.vlp.solvers._counting.estimate_target_count` on a nonnegative
    fit of the whole dictionary.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> from app.vlp.fingerprints import build_fingerprint
    >>> from app.vlp.measurements import measurement_from_amplitudes
    >>> from app.vlp.simulation import true_amplitudes
    >>> layout = paper_layout()
    >>> solver = OmpSolver(build_fingerprint(layout), "correlation")
    >>> amps = true_amplitudes(layout, layout.cell_centres(np.array([0, 399])))
    >>> solution = solver.solve(measurement_from_amplitudes(amps, "correlation", 16), 2)
    >>> sorted(solution.grid_indices.tolist())
    [0, 399]
    """

    name = "omp"
    description = "orthogonal matching pursuit on the grid (the paper's greedy algorithm)"

    def __init__(self, fingerprint: Fingerprint, model: Model) -> None:
        super().__init__(fingerprint, model)
        self.dictionary = GridDictionary(fingerprint, model)
        norms = self.dictionary.noise_free_norms
        # |correlation| is divided by the noise-free norm; unusable columns score 0
        self._score_scale = np.zeros_like(norms)
        np.divide(1.0, norms, out=self._score_scale, where=norms > _TINY)
        self._scored_transpose: FloatArray | None = None
        if self.dictionary.normalised is not None:
            self._scored_transpose = np.ascontiguousarray(
                (self.dictionary.normalised * self._score_scale).T
            )

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values
        scale = float(np.linalg.norm(values))
        target = values / scale
        dictionary = self.dictionary
        if n_targets is None:
            fit = nonnegative_fit(dictionary, target)
            n_targets = estimate_target_count(
                dictionary.weights(fit.cells, fit.coefficients, scale),
                max_targets=min(dictionary.usable.size, MAX_TARGETS),
            )
        if self._scored_transpose is not None:
            cells = self._select_dense(self._scored_transpose, target, n_targets)
        else:
            cells = self._select_large(target, n_targets)
        block, target_rows, rest_sq = dictionary.restrict(cells, target)
        coefficients, residual_norm = fit_least_squares(block, target_rows)
        return grid_solution(
            dictionary,
            cells,
            coefficients,
            scale=scale,
            residual_norm=float(np.hypot(residual_norm, np.sqrt(rest_sq))),
            n_iter=cells.size,
            converged=True,
        )

    def _pick(self, scores: FloatArray, support: list[int]) -> int:
        scores[support] = -1.0
        return int(np.argmax(scores))

    def _select_dense(
        self, scored_transpose: FloatArray, target: FloatArray, n_targets: int
    ) -> IntArray:
        """Greedy selection with an orthonormal basis of the chosen atoms, updated per step.

        The residual is ``target`` minus its projection on the noise atom and the chosen
        columns (Gram-Schmidt, applied twice for stability).
        """
        normalised = self.dictionary.normalised
        assert normalised is not None
        unit = self.dictionary.noise_unit
        basis = np.empty((target.size, n_targets + 1))
        basis[:, 0] = unit
        size = 1
        residual = target - (unit @ target) * unit
        support: list[int] = []
        for _ in range(n_targets):
            cell = self._pick(np.abs(scored_transpose @ residual), support)
            support.append(cell)
            atom = normalised[:, cell].copy()
            for _ in range(2):
                atom -= basis[:, :size] @ (basis[:, :size].T @ atom)
            length = float(np.linalg.norm(atom))
            if length > _TINY:
                atom /= length
                basis[:, size] = atom
                size += 1
                residual = residual - (atom @ residual) * atom
        return np.asarray(support, dtype=np.intp)

    def _select_large(self, target: FloatArray, n_targets: int) -> IntArray:
        """The same selection for dictionaries that are never materialised."""
        dictionary = self.dictionary
        unit = dictionary.noise_unit
        residual = target - (unit @ target) * unit
        support: list[int] = []
        for step in range(n_targets):
            scores = np.abs(dictionary.correlate(residual)) * self._score_scale
            support.append(self._pick(scores, support))
            if step + 1 < n_targets:
                cells = np.asarray(support, dtype=np.intp)
                block, target_rows, _ = dictionary.restrict(cells, target)
                coefficients = np.asarray(
                    np.linalg.lstsq(block, target_rows, rcond=None)[0], dtype=np.float64
                )
                residual = target - dictionary.predict(cells, coefficients)
        return np.asarray(support, dtype=np.intp)
