"""Matrix-free forward models with adjoints, checked by :func:`dottest`."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .typing import FloatArray

__all__ = ["CorrelationOperator", "dottest"]

# Grid columns per block in the adjoint: bounds the dense (block x M) temporary.
_ADJOINT_BLOCK_CELLS = 16_384


class CorrelationOperator:
    """Psi as an operator: ``theta -> vech(G diag(theta) G^T)`` and its adjoint.

    Parameters
    ----------
    scaled_gains : sparse array of shape (M, N)
        ``G = diag(x) H``.

    Notes
    -----
    The adjoint uses the identity ``(Psi^T r)_j = g_j^T R g_j``, where ``R`` is the symmetric
    matrix with ``r``'s diagonal entries on its diagonal and half of each off-diagonal entry
    on both sides (so each pair ``i < l`` counts once). Rows follow ``numpy.triu_indices(M)``.
    """

    def __init__(self, scaled_gains: sp.csr_array | sp.csr_matrix) -> None:
        self._gains = sp.csr_array(scaled_gains)
        self._gains_t = sp.csr_array(self._gains.T)
        self.n_leds = int(self._gains.shape[0])
        self.n_cells = int(self._gains.shape[1])
        self.shape = (self.n_leds * (self.n_leds + 1) // 2, self.n_cells)
        self._upper = np.triu_indices(self.n_leds)

    @property
    def gains_by_cell(self) -> sp.csr_array:
        """``G^T``, sparse of shape (N, M): row j holds grid point j's scaled gains."""
        return self._gains_t

    def matvec(self, theta: FloatArray) -> FloatArray:
        """``Psi @ theta``: theta of shape (N,) -> vech of shape (M(M+1)/2,)."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape != (self.n_cells,):
            raise ValueError(f"expected theta of shape ({self.n_cells},), got {theta.shape}")
        weighted = self._gains @ sp.diags_array(theta)
        corr = (weighted @ self._gains_t).toarray()
        return np.asarray(corr[self._upper])

    def rmatvec(self, residual: FloatArray) -> FloatArray:
        """``Psi^T @ r``: r of shape (M(M+1)/2,) -> shape (N,)."""
        residual = np.asarray(residual, dtype=np.float64)
        if residual.shape != (self.shape[0],):
            raise ValueError(f"expected a vech of shape ({self.shape[0]},), got {residual.shape}")
        half = np.zeros((self.n_leds, self.n_leds))
        half[self._upper] = residual
        symmetric = 0.5 * (half + half.T)  # diagonal kept whole, off-diagonals halved
        out = np.empty(self.n_cells)
        for start in range(0, self.n_cells, _ADJOINT_BLOCK_CELLS):
            block = self._gains_t[start : start + _ADJOINT_BLOCK_CELLS]  # (b, M) sparse
            projected = block @ symmetric  # (b, M) dense
            out[start : start + block.shape[0]] = np.asarray(
                block.multiply(projected).sum(axis=1)
            ).ravel()
        return out


def dottest(
    operator: CorrelationOperator,
    *,
    rng: np.random.Generator | int | None = None,
    rtol: float = 1e-10,
) -> bool:
    """Check ``<A u, v> == <u, A^T v>`` for random ``u``, ``v`` (PyLops' dot test)."""
    gen = np.random.default_rng(rng)
    u = gen.standard_normal(operator.shape[1])
    v = gen.standard_normal(operator.shape[0])
    left = float(operator.matvec(u) @ v)
    right = float(u @ operator.rmatvec(v))
    return abs(left - right) <= rtol * max(abs(left), abs(right), 1e-300)
