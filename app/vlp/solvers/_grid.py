"""Shared machinery of the grid solvers (``omp``, ``nnls``, ``l1``).

:class:`GridDictionary` holds the dictionary of one fingerprint and model -- ``J`` (M x N)
for ``power``, Psi (M(M+1)/2 x N) for ``correlation`` -- with unit-norm columns, plus the
unit-norm noise atom. Small problems keep the normalised dictionary dense; large ones
(``not fingerprint.is_dense`` or Psi above its dense limit) work from the sparse scaled
gains ``G`` and Psi's matrix-free operator, and only ever materialise the few rows and
columns a sub-problem touches (:meth:`GridDictionary.restrict`).

Every solve works on ``y / ||y||`` so that the numbers are of order one (raw entries of
``J`` are ~1e-10); :func:`grid_solution` converts back to the dictionary's own units.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt
import scipy.sparse as sp

from ..fingerprints import PSI_DENSE_LIMIT, Fingerprint
from ..measurements import Model, noise_atom, unvech, vech, vech_length
from ..typing import FloatArray, IntArray
from .base import Solution

__all__ = [
    "CANDIDATE_CELLS",
    "FULL_FIT_CELLS",
    "SCREENING_CELLS",
    "SCREENING_ROUNDS",
    "GridDictionary",
    "NonnegativeFit",
    "fit_least_squares",
    "fit_nonnegative",
    "grid_solution",
    "nonnegative_fit",
    "top_cells",
]

# Fit the whole dictionary when it is dense and has at most this many columns ...
FULL_FIT_CELLS = 5_000
# ... else start from this many columns best correlated with the measurement ...
CANDIDATE_CELLS = 200
# ... and add this many best correlated with the residual, for up to this many rounds.
SCREENING_CELLS = 100
SCREENING_ROUNDS = 3
# Eigenvalues this close to the median (relative to the largest; the adjoint then errs by at
# most this fraction of max|lambda| ||g_j||^2) are dropped by the large-room adjoint ...
_EIGEN_RTOL = 1e-11
# ... which projects the gains on this many eigenvectors at a time.
_EIGEN_BATCH = 8


class GridDictionary:
    """A fingerprint's dictionary for one model, column-normalised, with its noise atom.

    Parameters
    ----------
    fingerprint : Fingerprint
    model : {"power", "correlation"}

    Attributes
    ----------
    column_norms : ndarray of shape (N,)
        Euclidean norms of the raw columns (``J`` or Psi), squared amplitude units.
    noise_norm : float
        Norm of the raw noise atom (``sqrt(M)``).
    normalised : ndarray of shape (n_rows, N) or None
        The dense column-normalised dictionary, when it is small enough.
    """

    def __init__(self, fingerprint: Fingerprint, model: Model) -> None:
        self.fingerprint = fingerprint
        self.model = model
        n_leds = fingerprint.n_leds
        self.n_rows = n_leds if model == "power" else vech_length(n_leds)
        self.n_cells = fingerprint.n_cells
        noise = noise_atom(model, n_leds)
        self.noise_norm = float(np.linalg.norm(noise))
        self.noise_unit: FloatArray = noise / self.noise_norm
        self.normalised: FloatArray | None = None
        if fingerprint.is_dense and (
            model == "power" or self.n_rows * self.n_cells <= PSI_DENSE_LIMIT
        ):
            raw = np.asarray(
                fingerprint.power_matrix() if model == "power" else fingerprint.correlation_matrix()
            )
            self.column_norms: FloatArray = np.linalg.norm(raw, axis=0)
            self._inverse_norms = _safe_inverse(self.column_norms)
            self.normalised = raw * self._inverse_norms
        else:
            square_sums, fourth_sums = _column_power_sums(fingerprint.scaled_gains())
            self._square_sums = square_sums
            if model == "power":
                self.column_norms = np.sqrt(fourth_sums)
            else:  # ||vech(g g^T)||^2 = sum_{i<=l} g_i^2 g_l^2 = ((sum g^2)^2 + sum g^4) / 2
                self.column_norms = np.sqrt(0.5 * (square_sums**2 + fourth_sums))
            self._inverse_norms = _safe_inverse(self.column_norms)
        self.usable: IntArray = np.flatnonzero(self.column_norms > 0)
        # Norm of each normalised column once the noise atom's direction is projected out:
        # residuals of fits that include the noise atom are orthogonal to it.
        noise_overlap = self._noise_overlap() * self._inverse_norms
        self.noise_free_norms: FloatArray = np.sqrt(np.clip(1.0 - noise_overlap**2, 0.0, None))

    def _noise_overlap(self) -> FloatArray:
        """``u^T a_j`` for the raw columns a_j and the unit noise atom u; shape (N,)."""
        if self.normalised is not None:
            return np.asarray(self.noise_unit @ self.normalised) * self.column_norms
        # power: sum_i g_ij^2 / sqrt(M); correlation: the diagonal rows give the same sum.
        return self._square_sums / self.noise_norm

    @property
    def is_materialised(self) -> bool:
        """True when the normalised dictionary is held densely."""
        return self.normalised is not None

    def correlate(self, residual: FloatArray) -> FloatArray:
        """``D^T r`` with the column-normalised dictionary D; shape (N,)."""
        if self.normalised is not None:
            return np.asarray(self.normalised.T @ residual)
        if self.model == "power":
            raw = np.asarray(self.fingerprint.power_matrix().T @ residual)
        else:
            raw = self._correlation_adjoint(residual)
        return raw * self._inverse_norms

    def _correlation_adjoint(self, residual: FloatArray) -> FloatArray:
        """``Psi^T r`` through an eigendecomposition of the symmetric matrix behind ``r``.

        ``(Psi^T r)_j = g_j^T S g_j`` with ``S`` as in
        :class:`~app.vlp.operators.CorrelationOperator`. Writing
        ``S = c I + sum_e (lambda_e - c) u_e u_e^T`` with ``c`` the median eigenvalue gives
        ``c ||g_j||^2 + sum_e (lambda_e - c) (u_e^T g_j)^2``, where only eigenvalues away
        from ``c`` count. Aggregated correlations are sums of a few outer products plus a
        multiple of I (few terminals, fitted noise), so few terms remain and the adjoint
        costs a few sparse products instead of one dense M x M product per grid point.
        """
        half = unvech(residual, self.fingerprint.n_leds)
        symmetric = 0.5 * (half + np.diag(np.diag(half)))
        eigenvalues, eigenvectors = np.linalg.eigh(symmetric)
        shift = float(np.median(eigenvalues))
        spread = eigenvalues - shift
        keep = np.abs(spread) > _EIGEN_RTOL * max(float(np.max(np.abs(eigenvalues))), 1e-300)
        spread, eigenvectors = spread[keep], eigenvectors[:, keep]
        gains_t = self.fingerprint.scaled_gains().T  # (N, M), no copy
        out = shift * self._square_sums
        for start in range(0, spread.size, _EIGEN_BATCH):
            projected = np.asarray(gains_t @ eigenvectors[:, start : start + _EIGEN_BATCH])
            out = out + (projected**2) @ spread[start : start + _EIGEN_BATCH]
        return np.asarray(out)

    def restrict(self, cells: IntArray, target: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        """The sub-problem on some columns plus the noise atom.

        Parameters
        ----------
        cells : ndarray of shape (k,)
            Grid columns.
        target : ndarray of shape (n_rows,)
            The (scaled) measurement.

        Returns
        -------
        block : ndarray of shape (r, k + 1)
            Normalised columns, noise atom last, on the r rows where any of them is nonzero.
        target_rows : ndarray of shape (r,)
            ``target`` on those rows.
        rest_sq : float
            Squared norm of ``target`` on the other rows (a residual no fit can change).
        """
        cells = np.asarray(cells, dtype=np.intp)
        if self.normalised is not None:
            block = np.column_stack((self.normalised[:, cells], self.noise_unit))
            return block, target, 0.0
        gains = self._gain_columns(cells)
        if self.model == "power":
            block = np.column_stack((gains**2 * self._inverse_norms[cells], self.noise_unit))
            return block, target, 0.0
        rows = self._correlation_rows(np.flatnonzero(np.any(gains != 0, axis=1)))
        upper, lower = np.triu_indices(self.fingerprint.n_leds)
        pair_upper, pair_lower = upper[rows], lower[rows]
        columns = gains[pair_upper] * gains[pair_lower] * self._inverse_norms[cells]
        block = np.column_stack((columns, self.noise_unit[rows]))
        target_rows = target[rows]
        rest_sq = max(float(target @ target) - float(target_rows @ target_rows), 0.0)
        return block, target_rows, rest_sq

    def _correlation_rows(self, leds: IntArray) -> IntArray:
        """Rows (i, l), i <= l, with both LEDs in ``leds``, plus every diagonal row."""
        n_leds = self.fingerprint.n_leds
        first, second = np.meshgrid(leds, leds, indexing="ij")
        keep = first <= second
        i, l_ = first[keep], second[keep]
        pairs = i * n_leds - i * (i - 1) // 2 + (l_ - i)
        diagonal = np.arange(n_leds)
        diagonal = diagonal * n_leds - diagonal * (diagonal - 1) // 2
        return np.asarray(np.union1d(pairs, diagonal), dtype=np.intp)

    def predict(self, cells: IntArray, coefficients: FloatArray) -> FloatArray:
        """``D[:, cells] c + c_noise u`` on every row; ``coefficients`` has the noise last."""
        cells = np.asarray(cells, dtype=np.intp)
        prediction = coefficients[-1] * self.noise_unit
        if cells.size == 0:
            return np.asarray(prediction)
        if self.normalised is not None:
            return np.asarray(prediction + self.normalised[:, cells] @ coefficients[:-1])
        theta = self.weights(cells, coefficients[:-1], 1.0)
        gains = self._gain_columns(cells)
        if self.model == "power":
            return np.asarray(prediction + gains**2 @ theta)
        return np.asarray(prediction + vech((gains * theta) @ gains.T))

    def _gain_columns(self, cells: IntArray) -> FloatArray:
        """Columns of ``G`` as a dense (M, k) array."""
        return np.asarray(sp.csc_array(self.fingerprint.scaled_gains()[:, cells]).toarray())

    def weights(self, cells: IntArray, coefficients: FloatArray, scale: float) -> FloatArray:
        """Coefficients of normalised columns -> occupancies in the raw dictionary's units."""
        return np.asarray(coefficients * scale * self._inverse_norms[cells])


def _column_power_sums(gains: sp.csr_array) -> tuple[FloatArray, FloatArray]:
    """``sum_i g_ij^2`` and ``sum_i g_ij^4`` per column, without copying the matrix."""
    n_cells = int(gains.shape[1])
    powers = gains.data**2
    square_sums = np.bincount(gains.indices, weights=powers, minlength=n_cells)
    powers **= 2
    fourth_sums = np.bincount(gains.indices, weights=powers, minlength=n_cells)
    return np.asarray(square_sums, dtype=np.float64), np.asarray(fourth_sums, dtype=np.float64)


def _safe_inverse(norms: FloatArray) -> FloatArray:
    out = np.zeros_like(norms)
    np.divide(1.0, norms, out=out, where=norms > 0)
    return out


def fit_least_squares(block: FloatArray, target: FloatArray) -> tuple[FloatArray, float]:
    """Least squares on ``block`` (noise atom last) with the noise coefficient kept >= 0.

    If the unconstrained fit gives the noise atom a negative coefficient, the constrained
    optimum has it at 0 (a convex quadratic with one linear constraint), so the fit is
    repeated without it.

    Returns
    -------
    coefficients : ndarray of shape (k + 1,)
    residual_norm : float
    """
    coefficients: FloatArray = np.asarray(
        np.linalg.lstsq(block, target, rcond=None)[0], dtype=np.float64
    )
    if coefficients[-1] < 0:
        coefficients = np.append(np.linalg.lstsq(block[:, :-1], target, rcond=None)[0], 0.0)
    return coefficients, float(np.linalg.norm(block @ coefficients - target))


def fit_nonnegative(block: FloatArray, target: FloatArray) -> tuple[FloatArray, float]:
    """Nonnegative least squares on ``block``; returns coefficients and the residual norm."""
    coefficients, residual = sopt.nnls(block, target, maxiter=50 * block.shape[1])
    return np.asarray(coefficients), float(residual)


def top_cells(dictionary: GridDictionary, target: FloatArray, count: int) -> IntArray:
    """The ``count`` usable columns with the largest (signed) correlation with ``target``."""
    correlation = dictionary.correlate(target)[dictionary.usable]
    count = min(count, correlation.size)
    best = np.argpartition(-correlation, count - 1)[:count]
    return np.asarray(np.sort(dictionary.usable[best]), dtype=np.intp)


class NonnegativeFit:
    """A nonnegative fit of the whole dictionary (or of its best candidate columns).

    Attributes
    ----------
    cells : ndarray of shape (n,)
        Columns that took part.
    coefficients : ndarray of shape (n,)
        Their coefficients for the normalised columns and the scaled measurement.
    noise_coefficient : float
    residual_norm : float
        Of the scaled measurement.
    """

    def __init__(
        self,
        cells: IntArray,
        coefficients: FloatArray,
        noise_coefficient: float,
        residual_norm: float,
    ) -> None:
        self.cells = cells
        self.coefficients = coefficients
        self.noise_coefficient = noise_coefficient
        self.residual_norm = residual_norm


def nonnegative_fit(dictionary: GridDictionary, target: FloatArray) -> NonnegativeFit:
    """NNLS of the scaled measurement on the dictionary plus the noise atom.

    Uses every usable column when the dictionary is dense with at most
    :data:`FULL_FIT_CELLS` columns. Otherwise the fit is screened: start from the
    :data:`CANDIDATE_CELLS` columns best correlated with the measurement, then, for up to
    :data:`SCREENING_ROUNDS` rounds, add the columns best correlated with the current
    residual (so targets far apart each get candidates) and refit.
    """
    if dictionary.is_materialised and dictionary.n_cells <= FULL_FIT_CELLS:
        cells = dictionary.usable
        block, target_rows, rest_sq = dictionary.restrict(cells, target)
        coefficients, residual = fit_nonnegative(block, target_rows)
        return NonnegativeFit(
            cells,
            coefficients[:-1],
            float(coefficients[-1]),
            float(np.hypot(residual, np.sqrt(rest_sq))),
        )
    cells = top_cells(dictionary, target, CANDIDATE_CELLS)
    for round_ in range(SCREENING_ROUNDS + 1):
        block, target_rows, rest_sq = dictionary.restrict(cells, target)
        coefficients, residual = fit_nonnegative(block, target_rows)
        if round_ == SCREENING_ROUNDS:
            break
        keep = cells[coefficients[:-1] > 0]
        mismatch = target - dictionary.predict(
            keep, np.append(coefficients[:-1][coefficients[:-1] > 0], coefficients[-1])
        )
        new = np.setdiff1d(top_cells(dictionary, mismatch, SCREENING_CELLS), cells)
        if new.size == 0:
            break
        cells = np.union1d(cells, new)
    return NonnegativeFit(
        cells,
        coefficients[:-1],
        float(coefficients[-1]),
        float(np.hypot(residual, np.sqrt(rest_sq))),
    )


def grid_solution(
    dictionary: GridDictionary,
    cells: IntArray,
    coefficients: FloatArray,
    *,
    scale: float,
    residual_norm: float,
    n_iter: int,
    converged: bool,
) -> Solution:
    """Assemble a :class:`Solution` from a fit on normalised columns (noise coefficient last).

    Parameters
    ----------
    dictionary : GridDictionary
    cells : ndarray of shape (K,)
        The chosen grid columns.
    coefficients : ndarray of shape (K + 1,)
        Their coefficients and the noise atom's, for the scaled measurement ``y / scale``.
    scale : float
        ``||y||``, the measurement's scale.
    residual_norm : float
        Residual norm of the scaled measurement.
    n_iter : int
    converged : bool
    """
    cells = np.asarray(cells, dtype=np.intp)
    weights = dictionary.weights(cells, coefficients[:-1], scale)
    order = np.argsort(-weights, kind="stable")
    cells, weights = cells[order], weights[order]
    return Solution(
        positions=dictionary.fingerprint.layout.cell_centres(cells),
        grid_indices=cells,
        weights=weights,
        noise_power=float(coefficients[-1] * scale / dictionary.noise_norm),
        residual_norm=float(residual_norm * scale),
        n_iter=int(n_iter),
        converged=bool(converged),
    )
