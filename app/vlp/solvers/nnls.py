"""Nonnegative least squares on the grid: occupancies cannot be negative."""

from __future__ import annotations

import numpy as np

from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
from ..typing import FloatArray, IntArray
from ._counting import estimate_target_count
from ._grid import (
    GridDictionary,
    NonnegativeFit,
    fit_nonnegative,
    grid_solution,
    nonnegative_fit,
)
from .base import MAX_TARGETS, Solution, Solver, register_solver

__all__ = ["NnlsSolver", "select_support"]


@register_solver
class NnlsSolver(Solver):
    """NNLS on the column-normalised ``J`` or Psi plus the noise atom, then a K-term refit.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}

    Notes
    -----
    1. Solve ``min ||D c + s u - y||_2`` over ``c >= 0, s >= 0`` (``D`` the normalised
       dictionary, ``u`` the unit noise atom) on every grid column, or, for large rooms, on
       the :data:`~app.vlp.solvers._grid.CANDIDATE_CELLS` columns best correlated with y.
    2. Keep the K columns of largest occupancy (K given, or
       :func:`~app.vlp.solvers._counting.estimate_target_count` of the occupancies).
    3. Refit NNLS on those K columns and the noise atom; its coefficients are the reported
       weights (about 1 per terminal) and ``noise_power``.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> from app.vlp.fingerprints import build_fingerprint
    >>> from app.vlp.measurements import measurement_from_amplitudes
    >>> from app.vlp.simulation import true_amplitudes
    >>> layout = paper_layout()
    >>> solver = NnlsSolver(build_fingerprint(layout), "power")
    >>> amps = true_amplitudes(layout, layout.cell_centres(np.array([45, 310])))
    >>> solution = solver.solve(measurement_from_amplitudes(amps, "power", 16))
    >>> sorted(solution.grid_indices.tolist()), np.round(solution.weights, 6).tolist()
    ([45, 310], [1.0, 1.0])
    """

    name = "nnls"
    description = "nonnegative least squares on the grid, then a K-term refit"

    def __init__(self, fingerprint: Fingerprint, model: Model) -> None:
        super().__init__(fingerprint, model)
        self.dictionary = GridDictionary(fingerprint, model)

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values
        scale = float(np.linalg.norm(values))
        target = values / scale
        fit = nonnegative_fit(self.dictionary, target)
        cells = select_support(self.dictionary, fit, scale, n_targets)
        block, target_rows, rest_sq = self.dictionary.restrict(cells, target)
        coefficients, residual = fit_nonnegative(block, target_rows)
        return grid_solution(
            self.dictionary,
            cells,
            coefficients,
            scale=scale,
            residual_norm=float(np.hypot(residual, np.sqrt(rest_sq))),
            n_iter=2,
            converged=True,
        )


def select_support(
    dictionary: GridDictionary, fit: NonnegativeFit, scale: float, n_targets: int | None
) -> IntArray:
    """The K cells of a nonnegative fit with the largest occupancies.

    Parameters
    ----------
    dictionary : GridDictionary
    fit : NonnegativeFit
    scale : float
        ``||y||`` of the measurement the fit was made for.
    n_targets : int or None
        K; estimated from the occupancies when None.

    Returns
    -------
    cells : ndarray of shape (K,)
        Ties (e.g. zero occupancies when the fit has fewer than K nonzeros) are broken by
        the normalised coefficient, then by the correlation order of the candidates.
    """
    weights: FloatArray = dictionary.weights(fit.cells, fit.coefficients, scale)
    if n_targets is None:
        n_targets = estimate_target_count(
            weights, max_targets=min(MAX_TARGETS, dictionary.usable.size)
        )
    n_targets = min(n_targets, fit.cells.size)
    order = np.lexsort((-fit.coefficients, -weights))
    return np.asarray(fit.cells[order[:n_targets]], dtype=np.intp)
