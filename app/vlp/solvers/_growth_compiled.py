"""Compiled ADCG growth step of the ``gridless`` search: insert one target, refine briefly.

Stands in for :meth:`GridlessSolver._grow` in dense rooms with the correlation model during
the search (:meth:`GridlessSolver._compiled_growth` says when): the whitened residual of the
current state, the insertion scores of every grid point, the best one (away from the
points to avoid), and the short Levenberg-Marquardt refinement of positions and noise with
the new target, in one call instead of some sixty Python-level steps. It calls the same
kernels the Python path calls (:mod:`._fit_compiled`), in the same order, so the state it
returns is that path's to the bit; the Python path (and under ``VLP_KERNELS=reference`` its
NumPy kernels) is its reference. Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ..typing import FloatArray
from ._channel_compiled import ChannelConstants, TableConstants
from ._fit_compiled import (
    Problem,
    correlation_scores_kernel,
    lm_kernel,
    residual_kernel,
    whiten_kernel,
    whitening_kernel,
)
from ._kernels import compiled

__all__ = ["growth_step_kernel"]


@compiled
def growth_step_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    plug_in: bool,
    is_diag: FloatArray,
    values: FloatArray,
    positions: FloatArray,
    noise: float,
    heights: FloatArray,
    weights: FloatArray,
    log_gains: FloatArray,
    log_scale: float,
    receiver_height: float,
    gains: FloatArray,
    centres: FloatArray,
    avoid: FloatArray,
    avoid_radius: float,
    height_mean: float,
    layout: Problem,
    priors: Problem,
    lower: FloatArray,
    upper: FloatArray,
    inner_iter: int,
    initial_damping: float,
    tol: float,
    step_tol: float,
) -> tuple[FloatArray, float, int]:
    """One growth step of the state ``(positions (K, 2), noise, heights, weights,
    log_gains (K,), log_scale)``: the new positions (K + 1, 2), noise coefficient and LM
    iterations used (0 when ``inner_iter`` is 0: inserted, not refined).

    The step runs in the state's plug-in whitening when ``plug_in`` and K > 0
    (:meth:`Whitening.from_state`, ``is_diag`` the entries' diagonal indicator), else in
    ``white`` (the plain metric).

    ``gains`` (M, N) and ``centres`` (N, 2): the grid's scaled gains and points; ``avoid``
    (n, 2): points whose ``avoid_radius`` the insertion stays out of, unless that leaves
    none; ``layout``, ``priors``: the search priors' tuples (positions and noise only);
    ``lower``, ``upper``: the bounds of theta for K + 1 targets.
    """
    k = positions.shape[0]
    if k > 0:
        on_plane = True
        for i in range(k):
            on_plane = on_plane and heights[i] == receiver_height
        unit = log_scale == 0.0
        for i in range(k):
            unit = unit and log_gains[i] == 0.0 and weights[i] == 1.0
        fixed = (heights, weights, log_gains, log_scale, on_plane, unit)
        if plug_in:
            upper_index, lower_index = white[3], white[4]
            rotation, entry_weights = whitening_kernel(
                channel,
                table,
                positions,
                fixed,
                noise,
                float(k),
                True,
                upper_index,
                lower_index,
                is_diag,
            )
            weighted_diag = np.empty(entry_weights.shape[0])
            for col in range(entry_weights.shape[0]):
                weighted_diag[col] = entry_weights[col] * is_diag[col]
            white = (True, rotation, entry_weights, upper_index, lower_index, weighted_diag)
    data = whiten_kernel(white, values)
    if k == 0:
        residual = data
    else:
        theta = np.empty(2 * k + 1)
        for i in range(k):
            theta[i] = positions[i, 0]
            theta[k + i] = positions[i, 1]
        theta[2 * k] = noise
        residual = residual_kernel(channel, table, white, data, theta, fixed, layout, priors)[
            : data.shape[0]
        ].copy()
    num, norms = correlation_scores_kernel(white, residual, gains)
    weight = math.exp(log_scale)
    twice = 2.0 * weight
    squared = weight**2
    n_points = centres.shape[0]
    scores = np.empty(n_points)
    for j in range(n_points):
        scores[j] = twice * num[j] - squared * norms[j]
    if avoid.shape[0] > 0:
        allowed = scores.copy()
        radius2 = avoid_radius**2
        for p in range(avoid.shape[0]):
            for j in range(n_points):
                dx = centres[j, 0] - avoid[p, 0]
                dy = centres[j, 1] - avoid[p, 1]
                if dx**2 + dy**2 < radius2:
                    allowed[j] = -np.inf
        any_finite = False
        for j in range(n_points):
            any_finite = any_finite or np.isfinite(allowed[j])
        if any_finite:
            scores = allowed
    best = int(np.argmax(scores))
    grown_heights = np.empty(k + 1)
    grown_weights = np.empty(k + 1)
    grown_gains = np.empty(k + 1)
    grown_heights[:k] = heights
    grown_weights[:k] = weights
    grown_gains[:k] = log_gains
    grown_heights[k] = height_mean
    grown_weights[k] = 1.0
    grown_gains[k] = 0.0
    n = k + 1
    theta = np.empty(2 * n + 1)
    for i in range(k):
        theta[i] = positions[i, 0]
        theta[n + i] = positions[i, 1]
    theta[k] = centres[best, 0]
    theta[n + k] = centres[best, 1]
    theta[2 * n] = noise
    used = 0
    if inner_iter > 0:
        if upper[2 * n] < np.inf:
            # The state's noise may be above this objective's ceiling: start within bounds.
            for i in range(2 * n + 1):
                theta[i] = min(max(theta[i], lower[i]), upper[i])
        on_plane = True
        for i in range(n):
            on_plane = on_plane and grown_heights[i] == receiver_height
        unit = log_scale == 0.0
        for i in range(n):
            unit = unit and grown_gains[i] == 0.0 and grown_weights[i] == 1.0
        fixed = (grown_heights, grown_weights, grown_gains, log_scale, on_plane, unit)
        theta, _, used = lm_kernel(
            channel,
            table,
            white,
            data,
            theta,
            fixed,
            layout,
            priors,
            lower,
            upper,
            inner_iter,
            initial_damping,
            tol,
            step_tol,
        )
    out = np.empty((n, 2))
    for i in range(n):
        out[i, 0] = theta[i]
        out[i, 1] = theta[n + i]
    return out, theta[2 * n], used
