"""l1-norm minimisation with nonnegativity, the paper's convex solver (section III).

The problem, on the column-normalised dictionary ``D`` and unit noise atom ``u``, with the
measurement scaled to ``y = values / ||values||``::

    minimise    sum(c)                      (= ||c||_1 since c >= 0)
    subject to  ||D c + s u - y||_2 <= eps,  c >= 0,  s >= 0

is compiled once per solver object with ``y`` and ``eps`` as cvxpy Parameters and solved
by Clarabel with its ``qdldl`` direct method; :func:`solve_l1_fresh` builds the same
problem from scratch on every call, for benchmarks that measure what compiling once saves.
"""

from __future__ import annotations

import threading
import warnings
from typing import TYPE_CHECKING

import numpy as np

from ..errors import SolverError, SolverFailed
from ..fingerprints import Fingerprint
from ..measurements import Measurement, Model
from ..typing import FloatArray
from ._counting import estimate_target_count
from ._grid import (
    GridDictionary,
    NonnegativeFit,
    fit_nonnegative,
    grid_solution,
    nonnegative_fit,
)
from .base import MAX_TARGETS, Solution, Solver, register_solver
from .nnls import select_support

if TYPE_CHECKING:
    import cvxpy as cp

__all__ = ["DEFAULT_RESIDUAL_SLACK", "L1Problem", "L1Solver", "build_l1_problem", "solve_l1_fresh"]

# eps = (1 + slack) * (the smallest residual any nonnegative fit reaches) + floor * ||y||.
DEFAULT_RESIDUAL_SLACK = 0.1
_RESIDUAL_FLOOR = 1e-6
# cvxpy (with the scipy.stats it pulls in) is imported where a problem is built, not with this
# module: an API process that never serves the l1 solver does not hold it.
_SOLVER_OPTIONS: dict[str, object] = {"solver": "CLARABEL", "direct_solve_method": "qdldl"}


class L1Problem:
    """A compiled l1 problem: ``problem.solve()`` after setting ``target`` and ``eps``.

    :meth:`solve` holds a lock, so one object may serve several threads (one at a time).

    Attributes
    ----------
    problem : cvxpy.Problem
    coefficients : cvxpy.Variable of shape (N,)
    noise : cvxpy.Variable, scalar
    target : cvxpy.Parameter of shape (n_rows,)
    eps : cvxpy.Parameter, scalar, nonnegative
    """

    def __init__(self, dictionary: FloatArray, noise_unit: FloatArray) -> None:
        import cvxpy as cp
        from cvxpy.atoms.affine.sum import sum as cvx_sum
        from cvxpy.atoms.norm import norm as cvx_norm

        n_rows, n_cells = dictionary.shape
        self._lock = threading.Lock()
        self.coefficients = cp.Variable(n_cells, nonneg=True)
        self.noise = cp.Variable(nonneg=True)
        self.target = cp.Parameter(n_rows)
        self.eps = cp.Parameter(nonneg=True)
        residual = dictionary @ self.coefficients + self.noise * noise_unit - self.target
        self.problem = cp.Problem(
            cp.Minimize(cvx_sum(self.coefficients)), [cvx_norm(residual, 2) <= self.eps]
        )
        # compile now (cvxpy caches the parametrised reduction): solves only substitute
        self.target.value = np.zeros(n_rows)
        self.eps.value = 1.0
        self.problem.get_problem_data(cp.CLARABEL)

    def solve(self, target: FloatArray, eps: float) -> tuple[FloatArray, float]:
        """Solve for one scaled measurement; returns ``(c, s)``.

        Raises
        ------
        SolverError
            When Clarabel does not reach an optimal solution.
        """
        with self._lock:  # the Parameters are shared state; solver objects are cached
            self.target.value = target
            self.eps.value = eps
            return _run(self.problem, self.coefficients, self.noise)


def build_l1_problem(dictionary: FloatArray, noise_unit: FloatArray) -> L1Problem:
    """Compile the parametrised l1 problem for a dense normalised dictionary (n_rows, N)."""
    return L1Problem(dictionary, noise_unit)


def solve_l1_fresh(
    dictionary: FloatArray, noise_unit: FloatArray, target: FloatArray, eps: float
) -> tuple[FloatArray, float]:
    """The same problem with constants instead of Parameters, rebuilt on every call.

    Returns
    -------
    coefficients : ndarray of shape (N,)
    noise : float
    """
    import cvxpy as cp
    from cvxpy.atoms.affine.sum import sum as cvx_sum
    from cvxpy.atoms.norm import norm as cvx_norm

    coefficients = cp.Variable(dictionary.shape[1], nonneg=True)
    noise = cp.Variable(nonneg=True)
    residual = dictionary @ coefficients + noise * noise_unit - target
    problem = cp.Problem(cp.Minimize(cvx_sum(coefficients)), [cvx_norm(residual, 2) <= eps])
    return _run(problem, coefficients, noise)


def _run(
    problem: cp.Problem, coefficients: cp.Variable, noise: cp.Variable
) -> tuple[FloatArray, float]:
    import cvxpy as cp

    with warnings.catch_warnings():
        # cvxpy warns "Solution may be inaccurate" on OPTIMAL_INACCURATE; such a solution
        # still ranks the occupancies well, and the K-term NNLS refit fixes the weights.
        warnings.filterwarnings(
            "ignore", message="Solution may be inaccurate", category=UserWarning
        )
        problem.solve(**_SOLVER_OPTIONS)  # type: ignore[no-untyped-call]
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or coefficients.value is None:
        raise SolverFailed(
            f"l1 minimisation did not converge (status {problem.status!r})", field="solver"
        )
    return (
        np.clip(np.asarray(coefficients.value, dtype=np.float64), 0.0, None),
        max(float(np.asarray(noise.value)), 0.0),
    )


@register_solver
class L1Solver(Solver):
    """Nonnegative l1 minimisation (basis pursuit denoising), then a K-term NNLS refit.

    Parameters
    ----------
    fingerprint : Fingerprint
        Must be dense (``fingerprint.is_dense``) and, for the correlation model, small
        enough for Psi to be materialised.
    model : {"power", "correlation"}
    residual_slack : float, default=DEFAULT_RESIDUAL_SLACK
        Relative slack of ``eps`` over the smallest achievable residual.

    Raises
    ------
    SolverError
        On a fingerprint too large to hold the dictionary densely.

    Notes
    -----
    The paper solves eqs. (12) and (16) "using l1-norm minimization". We use the
    constrained (basis-pursuit-denoising) form, which is the faithful one -- minimise the
    l1 norm among all occupancy vectors that explain the measurement -- and make it robust
    by choosing ``eps`` per measurement: ``eps = (1 + slack) r_min + 1e-6 ||y||``, where
    ``r_min`` is the residual of a nonnegative least-squares fit of the same dictionary
    and noise atom, so the problem is always feasible (also off grid and with noise) and
    never looser than the data warrant. The K largest occupancies (K given or counted by
    :func:`~app.vlp.solvers._counting.estimate_target_count` on the NNLS occupancies) are
    then refitted by NNLS with the noise atom to remove the l1 shrinkage from the weights.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> from app.vlp.fingerprints import build_fingerprint
    >>> from app.vlp.measurements import measurement_from_amplitudes
    >>> from app.vlp.simulation import true_amplitudes
    >>> layout = paper_layout()
    >>> solver = L1Solver(build_fingerprint(layout), "correlation")
    >>> amps = true_amplitudes(layout, layout.cell_centres(np.array([45, 310])))
    >>> solution = solver.solve(measurement_from_amplitudes(amps, "correlation", 16), 2)
    >>> sorted(solution.grid_indices.tolist())
    [45, 310]
    """

    name = "l1"
    description = "nonnegative l1-norm minimisation on the grid (the paper's convex algorithm)"

    def __init__(
        self, fingerprint: Fingerprint, model: Model, residual_slack: float = DEFAULT_RESIDUAL_SLACK
    ) -> None:
        super().__init__(fingerprint, model)
        self.residual_slack = residual_slack
        self.dictionary = GridDictionary(fingerprint, model)
        if self.dictionary.normalised is None:
            raise SolverError(
                f"the l1 solver needs a dense dictionary; this room has {fingerprint.n_leds} "
                f"LEDs and {fingerprint.n_cells} grid points, too many -- use 'nnls' or 'omp'",
                field="solver",
            )
        self.program = build_l1_problem(self.dictionary.normalised, self.dictionary.noise_unit)

    def _solve(self, measurement: Measurement, n_targets: int | None) -> Solution:
        values = measurement.values
        scale = float(np.linalg.norm(values))
        target = values / scale
        dictionary = self.dictionary
        fit = nonnegative_fit(dictionary, target)
        if n_targets is None:
            n_targets = estimate_target_count(
                dictionary.weights(fit.cells, fit.coefficients, scale),
                max_targets=min(MAX_TARGETS, dictionary.usable.size),
            )
        eps = (1.0 + self.residual_slack) * fit.residual_norm + _RESIDUAL_FLOOR
        coefficients, noise = self.program.solve(target, eps)
        usable = dictionary.usable
        l1_fit = NonnegativeFit(usable, coefficients[usable], noise, 0.0)
        cells = select_support(dictionary, l1_fit, scale, n_targets)
        block, target_rows, rest_sq = dictionary.restrict(cells, target)
        refit, residual = fit_nonnegative(block, target_rows)
        return grid_solution(
            dictionary,
            cells,
            refit,
            scale=scale,
            residual_norm=float(np.hypot(residual, np.sqrt(rest_sq))),
            n_iter=1,
            converged=True,
        )
