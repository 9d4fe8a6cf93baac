"""Compiled scans of the power model in large rooms (line of sight only, ``G^T`` sparse): the
best grid point of a batch of tiles and the squared gains' products with a vector, each
reading ``G^T``'s CSR arrays in stored order (the order ``csr_matvec`` sums in), so the same
numbers as their NumPy references in :mod:`.gridless.local`. Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ...._kernels import compiled
from ....typing import FloatArray, IntArray

__all__ = ["best_of_tiles_kernel", "squared_gains_dot_kernel"]


@compiled
def best_of_tiles_kernel(
    tiles: IntArray,
    grid: tuple[int, int, int],
    by_cell: tuple[IntArray, IntArray, FloatArray],
    inverse_scale: float,
    residual: FloatArray,
    fourth_sums: FloatArray,
    factors: tuple[float, float, float],
) -> tuple[int, float, float]:
    """:func:`.gridless.local.best_of_tiles_reference` without the sparse row copies: the same
    operations per grid point (its row's entries in stored order, as ``csr_matvec`` sums
    them), so the same numbers.

    ``grid``: ``(n_x, n_y, tile)``; ``by_cell``: ``G^T``'s ``(indptr, indices, data)``;
    ``factors``: ``(2 w, w^2, norm_scale)``.
    """
    n_x, n_y, tile = grid
    indptr, indices, data = by_cell
    twice_weight, weight_sq, norm_scale = factors
    n_ty = -(-n_y // tile)
    best_cell, best_score, best_norm = -1, -math.inf, 0.0
    for t in tiles:
        tx, ty = divmod(t, n_ty)
        for ix in range(tx * tile, min((tx + 1) * tile, n_x)):
            for iy in range(ty * tile, min((ty + 1) * tile, n_y)):
                cell = ix * n_y + iy
                num = 0.0
                for at in range(indptr[cell], indptr[cell + 1]):
                    scaled = data[at] * inverse_scale
                    num += scaled * scaled * residual[indices[at]]
                norm = norm_scale * fourth_sums[cell]
                score = twice_weight * num - weight_sq * norm
                if score > best_score or (score == best_score and cell < best_cell):
                    best_cell, best_score, best_norm = cell, score, norm
    return best_cell, best_score, best_norm


@compiled
def squared_gains_dot_kernel(
    by_cell: tuple[IntArray, IntArray, FloatArray],
    inverse_scale: float,
    vector: FloatArray,
    fourth: bool,
) -> FloatArray:
    """:func:`.gridless.local.squared_gains_dot_reference` without the squared copy: each
    row's entries in stored order, as ``csr_matvec`` sums them (the same numbers)."""
    indptr, indices, data = by_cell
    n_cells = indptr.shape[0] - 1
    out = np.zeros(n_cells)
    for cell in range(n_cells):
        total = 0.0
        for at in range(indptr[cell], indptr[cell + 1]):
            scaled = data[at] * inverse_scale
            squared = scaled * scaled
            if fourth:
                squared = squared * squared
            total += squared * vector[indices[at]]
        out[cell] = total
    return out
