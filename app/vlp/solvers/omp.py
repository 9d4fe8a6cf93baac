"""Orthogonal matching pursuit, the paper's greedy solver (section III)."""

from __future__ import annotations

import numpy as np

from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
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

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values
        scale = float(np.linalg.norm(values))
        target = values / scale
        dictionary = self.dictionary
        if n_targets is None:
            fit = nonnegative_fit(dictionary, target)
            n_targets = estimate_target_count(
                dictionary.weights(fit.cells, fit.coefficients, scale),
                max_targets=min(dictionary.usable.size, MAX_TARGETS))
        support: list[int] = []
        block, target_rows, rest_sq = dictionary.restrict(np.array([], dtype=np.intp), target)
        coefficients, residual_norm = fit_least_squares(block, target_rows)
        residual = target - dictionary.predict(np.asarray(support, dtype=np.intp), coefficients)
        for _ in range(n_targets):
            correlation = np.abs(dictionary.correlate(residual))
            np.divide(correlation, dictionary.noise_free_norms, out=correlation,
                      where=dictionary.noise_free_norms > _TINY)
            correlation[dictionary.noise_free_norms <= _TINY] = -1.0
            correlation[support] = -1.0
            support.append(int(np.argmax(correlation)))
            cells = np.asarray(support, dtype=np.intp)
            block, target_rows, rest_sq = dictionary.restrict(cells, target)
            coefficients, residual_norm = fit_least_squares(block, target_rows)
            residual_norm = float(np.hypot(residual_norm, np.sqrt(rest_sq)))
            if len(support) < n_targets:
                residual = target - dictionary.predict(cells, coefficients)
        return grid_solution(
            dictionary, np.asarray(support, dtype=np.intp), coefficients, scale=scale,
            residual_norm=residual_norm, n_iter=len(support), converged=True)
