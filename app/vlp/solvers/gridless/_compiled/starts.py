"""Compiled choice of a terminal's weighted-pass starts: each grid cell's weighted cost with
the gain profiled out, and the best cells that beat the previous optimum's surroundings, in
one pass over the grid per terminal (no (K, N) temporaries). The NumPy reference, which
documents the rule, is :func:`.gridless.terminal_solve.profile_cells_reference`; its sums
run in another order (BLAS), so the costs agree to round-off and the cells chosen are the
same but where two cells' costs tie to round-off. Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ...._kernels import compiled
from ....typing import FloatArray, IntArray

__all__ = ["profile_cells_kernel"]


@compiled
def profile_cells_kernel(
    values: FloatArray,
    weights: FloatArray,
    gains: FloatArray,
    gains_sq: FloatArray,
    centres: FloatArray,
    previous: FloatArray,
    log_gain_sd: float,
    spacing: float,
    count: int,
) -> IntArray:
    """:func:`.gridless.terminal_solve.profile_cells_reference`: up to ``count`` cells per
    terminal, -1 padded, shape (K, count); ``log_gain_sd`` <= 0: no gain prior."""
    n_terminals, n_leds = values.shape
    n_cells = gains.shape[1]
    cells = np.full((n_terminals, count), -1, dtype=np.int64)
    across = np.empty(n_cells)
    energy = np.empty(n_cells)
    cost = np.empty(n_cells)
    eligible = np.empty(n_cells, dtype=np.bool_)
    for k in range(n_terminals):
        data = 0.0
        across[:] = 0.0
        energy[:] = 0.0
        # LED by LED over the grid: G's rows are contiguous.
        for m in range(n_leds):
            weight = weights[k, m]
            weighted = weight * values[k, m]
            data += weight * (values[k, m] * values[k, m])
            for n in range(n_cells):
                across[n] += weighted * gains[m, n]
                energy[n] += weight * gains_sq[m, n]
        for n in range(n_cells):
            gain = 1.0
            if energy[n] > 0.0:
                gain = min(max(across[n] / energy[n], 1e-3), 1e3)
            cost[n] = data - 2.0 * gain * across[n] + gain * gain * energy[n]
            if log_gain_sd > 0.0:
                prior = math.log(gain) / log_gain_sd
                cost[n] += prior * prior
        # The lowest cost around the previous optimum (NaN if any is: nothing beats it).
        x, y = previous[k, 0], previous[k, 1]
        around = False
        threshold = math.inf
        for n in range(n_cells):
            if math.hypot(centres[n, 0] - x, centres[n, 1] - y) < spacing:
                if not (around and (math.isnan(threshold) or cost[n] >= threshold)):
                    threshold = cost[n]
                around = True
        for n in range(n_cells):
            eligible[n] = cost[n] < threshold if around else True
        for chosen in range(count):
            # The lowest eligible cost, the first of ties (the first NaN, as argmin).
            best = -1
            for n in range(n_cells):
                if eligible[n]:
                    if math.isnan(cost[n]):
                        best = n
                        break
                    if best < 0 or cost[n] < cost[best]:
                        best = n
            if best < 0 or not math.isfinite(cost[best]):
                break
            cells[k, chosen] = best
            x, y = centres[best, 0], centres[best, 1]
            for n in range(n_cells):
                if eligible[n] and not math.hypot(centres[n, 0] - x, centres[n, 1] - y) >= spacing:
                    eligible[n] = False
    return cells
