"""Compiled grid scans of the correlation model in dense rooms: the insertion scores
(reference :func:`..fitting.grid_correlations`) and the far-optimum profiles (reference
:func:`..report.computed_profiles`).
"""

from __future__ import annotations

import numpy as np

from ...._kernels import compiled
from ....typing import FloatArray
from .fit import Problem


@compiled
def correlation_scores_kernel(
    white: Problem, residual: FloatArray, gains: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``<c psi_j, r>`` and ``||c psi_j||^2`` of every grid point (dense correlation model,
    gains (M, N)), the reference being ``gridless.fitting.grid_correlations``.

    With ``rot = U^T G``: ``<c psi_j, r> = rot_j^T Q rot_j`` for ``Q`` the symmetrised
    weighted residual in the rotated basis, and ``||c psi_j||^2 = sq_j^T C sq_j`` for
    ``sq = rot o rot`` and ``C`` the symmetrised squared weights.
    """
    has_rotation, rotation, weights, upper, lower, _ = white
    n_leds = gains.shape[0]
    quadratic = np.zeros((n_leds, n_leds))
    squared = np.zeros((n_leds, n_leds))
    for col in range(upper.shape[0]):
        a, b = upper[col], lower[col]
        w = weights[col]
        if a == b:
            quadratic[a, a] = w * residual[col]
            squared[a, a] = w * w
        else:
            quadratic[a, b] = quadratic[b, a] = 0.5 * w * residual[col]
            squared[a, b] = squared[b, a] = 0.5 * w * w
    rotated = np.dot(rotation.T.copy(), gains) if has_rotation else gains
    num, norms = _quadratic_forms(rotated, quadratic, squared)
    return num, norms


@compiled
def _quadratic_forms(
    points: FloatArray, quadratic: FloatArray, squared: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per column ``rho`` of ``points`` (M, N): ``rho^T Q rho`` and ``(rho o rho)^T S
    (rho o rho)``, shapes (N,)."""
    n_leds, n_points = points.shape
    squares = points * points
    left = np.dot(quadratic, points)
    right = np.dot(squared, squares)
    num = np.zeros(n_points)
    norms = np.zeros(n_points)
    for a in range(n_leds):
        for j in range(n_points):
            num[j] += points[a, j] * left[a, j]
            norms[j] += squares[a, j] * right[a, j]
    return num, norms


@compiled
def correlation_profiles_kernel(
    white: Problem,
    residual: FloatArray,
    gains: FloatArray,
    targets: FloatArray,
    multipliers: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """``gridless.report.profiles`` (dense correlation model), its NumPy code being the
    reference: with ``a_j`` the whitened unit atom of grid point j (gains (M, N)) and
    ``a_k`` that of estimate k (its gains ``targets[:, k]``, (M, K), and effective weight
    ``multipliers[k]``), the inner products ``<a_j, r + w_k a_k>`` (K, N), ``||a_j||^2``
    (N,), ``<a_k, r>`` and ``||a_k||^2`` (K,), and from them what each estimate explains at
    every grid point (K, N) and at its best (K,), as ``gridless.report.explained_profiles``.

    In the rotated basis (``rho = U^T g``) ``<a_j, r> = rho_j^T Q rho_j`` with ``Q`` the
    symmetric form of the weighted residual, and ``<a_j, a_k> = (rho_j o rho_k)^T S
    (rho_j o rho_k)`` with ``S`` that of the squared weights (each off-diagonal entry split
    over its two places).
    """
    has_rotation, rotation, weights, upper, lower, _ = white
    n_leds, n_points = gains.shape
    n_targets = targets.shape[1]
    quadratic = np.zeros((n_leds, n_leds))
    squared = np.zeros((n_leds, n_leds))
    for col in range(upper.shape[0]):
        a, b = upper[col], lower[col]
        half_value = 0.5 * weights[col] * residual[col]
        half_square = 0.5 * weights[col] * weights[col]
        quadratic[a, b] += half_value
        quadratic[b, a] += half_value
        squared[a, b] += half_square
        squared[b, a] += half_square
    if has_rotation:
        rotation_t = rotation.T.copy()
        grid = np.dot(rotation_t, gains)
        rotated = np.dot(rotation_t, targets)
    else:
        grid = gains.copy()
        rotated = targets.copy()
    num, norms = _quadratic_forms(grid, quadratic, squared)
    without = np.empty((n_targets, n_points))
    own_num = np.zeros(n_targets)
    own_norm = np.zeros(n_targets)
    weighted = np.empty((n_leds, n_leds))
    for k in range(n_targets):
        for a in range(n_leds):
            for b in range(n_leds):
                weighted[a, b] = squared[a, b] * rotated[a, k] * rotated[b, k]
                own_num[k] += rotated[a, k] * quadratic[a, b] * rotated[b, k]
                own_norm[k] += weighted[a, b] * rotated[a, k] * rotated[b, k]
        cross = np.dot(weighted, grid)
        for j in range(n_points):
            without[k, j] = num[j]
        for a in range(n_leds):
            for j in range(n_points):
                without[k, j] += multipliers[k] * grid[a, j] * cross[a, j]
    # np.maximum's and the largest's NaN and bounds, element by element.
    explained = np.empty((n_targets, n_points))
    best = np.empty(n_targets)
    for k in range(n_targets):
        for j in range(n_points):
            value = without[k, j]
            value = 0.0 if value < 0.0 else value
            norm = norms[j]
            norm = 1e-300 if norm < 1e-300 else norm
            explained[k, j] = value * value / norm
        top = explained[k, 0]
        for j in range(1, n_points):
            value = explained[k, j]
            if value > top or value != value:
                top = value
                if value != value:
                    break
        weight = multipliers[k]
        own = 2.0 * weight * own_num[k] + weight * weight * own_norm[k]
        best[k] = top if (top >= own or top != top) else own
    return explained, best
