"""Compiled covariance of a ``gridless`` answer: the model-error sandwich in one call.

Stands in for the NumPy path of :func:`.gridless.uncertainty.fit_uncertainty` (its reference, with
:func:`.gridless.uncertainty.misfit_columns`, :func:`.gridless.uncertainty.perturbation_columns`,
:func:`.gridless.uncertainty.shape_gradients` and, in :mod:`app.vlp.uncertainty`,
:func:`misfit_design_reference`, :func:`fit_misfit` and :func:`predictive_covariances`, whose
docstrings give the method). Every answer pays for it, and in NumPy it is some forty small
calls. Arguments are the tuples of :mod:`.gridless._compiled.fit`. Private: callers validate.

The pieces are separate kernels so that each can be compared with its reference:

- :func:`misfit_columns_kernel`: the whitened model-error columns ``F`` of all kinds side
  by side, shape (L, Q), and each kind's number of columns.
- :func:`misfit_design_kernel`: the :class:`app.vlp.uncertainty.MisfitDesign` arrays.
- :func:`fit_misfit_kernel`: :func:`app.vlp.uncertainty.fit_misfit` for one fit with a
  fitted noise variance (at most ``max_noise``), with a Lawson-Hanson NNLS.
- :func:`predictive_covariances_kernel`: the widened (K, 2, 2) position covariances.
- :func:`sandwich_covariances_kernel`: all of them from the fit's ``[J | r]``.
"""

from __future__ import annotations

import math

import numpy as np

from ...._kernels import compiled
from ....typing import FloatArray, IntArray
from .channel import (
    ChannelConstants,
    TableConstants,
    beam_towards,
    channel_fields,
    channel_rows_kernel,
)
from .fit import Problem, _augmented, _multipliers, _symmetric_product

__all__ = [
    "fit_misfit_kernel",
    "misfit_columns_kernel",
    "misfit_design_kernel",
    "nnls_kernel",
    "predictive_covariances_kernel",
    "sandwich_covariances_kernel",
]

# As app.vlp.uncertainty (imported there would be circular through the solvers package).
_MISFIT_REWEIGHTS = 4
_PINV_RCOND = 1e-15  # numpy.linalg.pinv's default cut-off, relative to the largest
_LEVEL = 0.95
_EPS = 2.220446049250313e-16  # float64 machine epsilon


@compiled
def _perturb(
    white: Problem,
    rotated: FloatArray,
    moved: FloatArray,
    scales: FloatArray,
    out: FloatArray,
    at: int,
) -> None:
    """Columns ``at ..`` of ``out``: the whitened change of the model per unit of each
    target's direction, ``(moved_a rot_b + rot_a moved_b) w_k c_l`` (``moved`` (M', K, n),
    ``rotated`` (M', K), ``scales`` the multipliers ``w_k``)."""
    _, _, weights, upper, lower, _ = white
    n_targets, n_dirs = moved.shape[1], moved.shape[2]
    for col in range(upper.shape[0]):
        a, b = upper[col], lower[col]
        for k in range(n_targets):
            factor = scales[k] * weights[col]
            for n in range(n_dirs):
                value = moved[a, k, n] * rotated[b, k] + rotated[a, k] * moved[b, k, n]
                out[col, at + k * n_dirs + n] = value * factor


@compiled
def misfit_columns_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    level: bool,
) -> tuple[FloatArray, IntArray]:
    """``gridless.uncertainty.misfit_columns`` side by side: each target's relative error per LED
    (K M columns), its photodiode's tilt (2 K; zeros when ``level``, the layout's
    photodiodes facing straight up), and its height (K) unless heights are fitted; and the
    number of columns of each kind."""
    fields = channel_fields(channel)
    led_x, led_y, led_z = fields[0], fields[1], fields[2]
    free_height_factor, orders, half_exponent = fields[5], fields[6], fields[7]
    cos_fov2 = fields[10]
    beamed = fields[14]
    heights, _, _, _, on_plane, _ = fixed
    has_rotation, rotation = white[0], white[1]
    k = heights.shape[0]
    n_leds = led_x.shape[0]
    xs = theta[:k].copy()
    ys = theta[k : 2 * k].copy()
    gains = channel_rows_kernel(channel, table, xs, ys, heights, on_plane)[0]  # (K, M)
    heights_free = layout[0] == 3
    kinds = 2 if heights_free else 3
    sizes = np.empty(kinds, dtype=np.int64)
    sizes[0], sizes[1] = k * n_leds, 2 * k
    if not heights_free:
        sizes[2] = k
    _, multipliers = _multipliers(theta, fixed, layout)
    length = white[2].shape[0]
    out = np.empty((length, sizes.sum()))
    # Target k's gains and their directions in the whitening's basis.
    rotated = np.empty((n_leds, k))
    for a in range(n_leds):
        for i in range(k):
            if has_rotation:
                total = 0.0
                for b in range(n_leds):
                    total += rotation[b, a] * gains[i, b]
                rotated[a, i] = total
            else:
                rotated[a, i] = gains[i, a]
    # Relative errors: direction n of target k is g_kn e_n.
    moved = np.empty((n_leds, k, n_leds))
    for a in range(n_leds):
        for i in range(k):
            for n in range(n_leds):
                if has_rotation:
                    moved[a, i, n] = rotation[n, a] * gains[i, n]
                else:
                    moved[a, i, n] = gains[i, n] if a == n else 0.0
    _perturb(white, rotated, moved, multipliers, out, 0)
    # Tilt and height: line-of-sight tilt derivatives h / v_z (v_x, v_y), and dg/dz.
    shape = np.zeros((n_leds, k, 3))
    free = channel_rows_kernel(channel, table, xs, ys, heights, False)
    for i in range(k):
        for m in range(n_leds):
            off_x = led_x[m] - xs[i]
            off_y = led_y[m] - ys[i]
            drop = max(led_z[m] - heights[i], 1e-9)
            dist2 = off_x * off_x + off_y * off_y + drop * drop
            shape[m, i, 0] = free[3, i, m]
            if not level and drop * drop >= cos_fov2 * dist2:
                los = (
                    free_height_factor[m]
                    * math.pow(drop, orders[m] + 1.0)
                    * math.pow(dist2, -half_exponent[m])
                )
                if beamed[m]:
                    los *= beam_towards(channel, m, -off_x, -off_y, -drop)[0]
                shape[m, i, 1] = los / drop * off_x
                shape[m, i, 2] = los / drop * off_y
    for part in range(kinds - 1):
        first = 1 if part == 0 else 0
        n_dirs = 2 if part == 0 else 1
        moved = np.empty((n_leds, k, n_dirs))
        for a in range(n_leds):
            for i in range(k):
                for n in range(n_dirs):
                    if has_rotation:
                        total = 0.0
                        for b in range(n_leds):
                            total += rotation[b, a] * shape[b, i, first + n]
                        moved[a, i, n] = total
                    else:
                        moved[a, i, n] = shape[a, i, first + n]
        _perturb(white, rotated, moved, multipliers, out, sizes[0] + part * sizes[1])
    return out, sizes


@compiled
def _pinv_symmetric(matrix: FloatArray) -> FloatArray:
    """``numpy.linalg.pinv(matrix, hermitian=True)``: ``U diag(1 / lam) U^T`` over the
    eigenvalues above ``1e-15`` of the largest magnitude."""
    lam, vectors = np.linalg.eigh(matrix)
    n = lam.shape[0]
    largest = 0.0
    for i in range(n):
        largest = max(largest, abs(lam[i]))
    cutoff = _PINV_RCOND * largest
    out = np.zeros((n, n))
    for i in range(n):
        if abs(lam[i]) > cutoff:
            inverse = 1.0 / lam[i]
            for a in range(n):
                scaled = vectors[a, i] * inverse
                for b in range(n):
                    out[a, b] += scaled * vectors[b, i]
    return out


@compiled
def misfit_design_kernel(
    jacobian: FloatArray, normal: FloatArray, columns: FloatArray, sizes: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`app.vlp.uncertainty.misfit_design_reference` with the error columns of every kind side
    by side (``sizes`` of them each): ``(inverse, data_normal, prior_normal, error_normals,
    noise_leverage, error_leverages, error_spread)``."""
    n_data, n_params = jacobian.shape
    inverse = _pinv_symmetric(normal)
    data_normal = np.dot(jacobian.T, jacobian)
    projected = np.dot(jacobian, inverse)
    hat = np.dot(projected, data_normal)
    noise_leverage = np.empty(n_data)
    for row in range(n_data):
        diagonal = 0.0
        square = 0.0
        for p in range(n_params):
            diagonal += projected[row, p] * jacobian[row, p]
            square += hat[row, p] * projected[row, p]
        noise_leverage[row] = max(1.0 - 2.0 * diagonal + square, 0.0)
    n_components = sizes.shape[0]
    error_normals = np.zeros((n_components, n_params, n_params))
    error_leverages = np.zeros((n_data, n_components))
    error_spread = np.zeros(n_components)
    seen_all = np.dot(jacobian.T, columns)  # (P, Q)
    absorbed_all = columns - np.dot(projected, seen_all)  # Q F
    at = 0
    for component in range(n_components):
        width = sizes[component]
        seen = np.ascontiguousarray(seen_all[:, at : at + width])
        absorbed = np.ascontiguousarray(absorbed_all[:, at : at + width])
        error_normals[component] = np.dot(seen, seen.T)
        for row in range(n_data):
            total = 0.0
            for q in range(width):
                total += absorbed[row, q] * absorbed[row, q]
            error_leverages[row, component] = total
        if width <= n_data:
            gram_matrix = np.dot(absorbed.T, absorbed)
        else:
            gram_matrix = np.dot(absorbed, absorbed.T)
        error_spread[component] = np.sum(gram_matrix * gram_matrix)
        at += width
    return (
        inverse,
        data_normal,
        normal - data_normal,
        error_normals,
        noise_leverage,
        error_leverages,
        error_spread,
    )


@compiled
def _least_squares(matrix: FloatArray, columns: IntArray, target: FloatArray) -> FloatArray:
    """``argmin ||A[:, columns] x - b||`` by Householder QR (a handful of columns: LAPACK's
    setup costs more than the arithmetic); a column with no part independent of those
    before it, relative to its own size, gets 0."""
    n_rows = matrix.shape[0]
    count = columns.shape[0]
    work = np.empty((n_rows, count))
    for i in range(n_rows):
        for c in range(count):
            work[i, c] = matrix[i, columns[c]]
    rhs = target.copy()
    sizes = np.zeros(count)
    for c in range(count):
        for i in range(n_rows):
            sizes[c] = max(sizes[c], abs(work[i, c]))
    for j in range(min(count, n_rows)):
        norm = 0.0
        for i in range(j, n_rows):
            norm += work[i, j] * work[i, j]
        norm = math.sqrt(norm)
        if norm == 0.0:
            continue
        alpha = -norm if work[j, j] > 0.0 else norm
        # v = a_j - alpha e_j, kept in place below the diagonal; |v|^2 = 2 norm (norm + |a_jj|)
        v_head = work[j, j] - alpha
        v_norm2 = v_head * v_head
        for i in range(j + 1, n_rows):
            v_norm2 += work[i, j] * work[i, j]
        if v_norm2 == 0.0:
            continue
        for c in range(j + 1, count):
            dot = v_head * work[j, c]
            for i in range(j + 1, n_rows):
                dot += work[i, j] * work[i, c]
            factor = 2.0 * dot / v_norm2
            work[j, c] -= factor * v_head
            for i in range(j + 1, n_rows):
                work[i, c] -= factor * work[i, j]
        dot = v_head * rhs[j]
        for i in range(j + 1, n_rows):
            dot += work[i, j] * rhs[i]
        factor = 2.0 * dot / v_norm2
        rhs[j] -= factor * v_head
        for i in range(j + 1, n_rows):
            rhs[i] -= factor * work[i, j]
        work[j, j] = alpha
    out = np.zeros(count)
    for j in range(min(count, n_rows) - 1, -1, -1):
        if abs(work[j, j]) <= _EPS * max(n_rows, count) * sizes[j]:
            continue
        total = rhs[j]
        for c in range(j + 1, count):
            total -= work[j, c] * out[c]
        out[j] = total / work[j, j]
    return out


@compiled
def nnls_kernel(matrix: FloatArray, target: FloatArray) -> FloatArray:
    """``argmin ||A x - b||`` over ``x >= 0`` (Lawson and Hanson's active set, the method
    of :func:`scipy.optimize.nnls`; at most ``3 n`` inner steps, as there).

    Round-off is judged column by column, relative to the column's own size: a fit's
    model-error columns can be 20 orders of magnitude below its noise column while they
    are the only ones that reach some rows
    (docs/explanation/real-rooms.md#rooms-nobody-tuned-it-for)."""
    n_rows, n = matrix.shape
    x = np.zeros(n)
    passive = np.zeros(n, dtype=np.bool_)
    tols = np.empty(n)
    for j in range(n):
        column = 0.0
        for i in range(n_rows):
            column += abs(matrix[i, j])
        tols[j] = 10.0 * max(n_rows, n) * _EPS * max(column, 1e-300)
    tol = tols.max()
    steps = 0
    for _ in range(3 * n):
        gradient = np.dot(matrix.T, target - np.dot(matrix, x))
        best, enter = 0.0, -1
        for j in range(n):
            if not passive[j] and gradient[j] > tols[j] and gradient[j] > best:
                best, enter = gradient[j], j
        if enter < 0:
            break
        passive[enter] = True
        while True:
            steps += 1
            count = 0
            for j in range(n):
                if passive[j]:
                    count += 1
            chosen = np.empty(count, dtype=np.int64)
            at = 0
            for j in range(n):
                if passive[j]:
                    chosen[at] = j
                    at += 1
            solved = _least_squares(matrix, chosen, target)
            trial = np.zeros(n)
            for c in range(count):
                trial[chosen[c]] = solved[c]
            feasible = True
            for c in range(count):
                if trial[chosen[c]] <= 0.0:
                    feasible = False
            if feasible or steps > 3 * n:
                x = trial
                for j in range(n):
                    if not passive[j] or x[j] < 0.0:
                        x[j] = 0.0
                break
            alpha = 1.0
            for c in range(count):
                j = chosen[c]
                if trial[j] <= 0.0:
                    # x[j] >= 0: a zero gap means both are 0 (a column that just entered
                    # and got no independent part), and the limit of the ratio is 0.
                    gap = x[j] - trial[j]
                    alpha = min(alpha, x[j] / gap if gap > 0.0 else 0.0)
            for j in range(n):
                x[j] += alpha * (trial[j] - x[j])
            for c in range(count):
                j = chosen[c]
                if x[j] <= tol:
                    x[j] = 0.0
                    passive[j] = False
    return x


@compiled
def fit_misfit_kernel(
    residual: FloatArray,
    noise_leverage: FloatArray,
    error_leverages: FloatArray,
    error_spread: FloatArray,
    max_noise: float,
) -> tuple[float, FloatArray, FloatArray]:
    """:func:`app.vlp.uncertainty.fit_misfit` of one fit with the noise variance fitted, at
    most ``max_noise``: ``(noise, model_errors, dofs)``."""
    n_data, n_components = error_leverages.shape
    squares = residual * residual
    dofs = np.empty(n_components + 1)
    dofs[0] = noise_leverage.sum()
    for c in range(n_components):
        trace = error_leverages[:, c].sum()
        spread = error_spread[c]
        dofs[1 + c] = trace * trace / max(spread, 1e-300) if spread > 0.0 else 0.0
    design = np.empty((n_data, n_components + 1))
    design[:, 0] = noise_leverage
    design[:, 1:] = error_leverages
    if not np.any(design != 0.0):
        return 1.0, np.zeros(n_components), dofs
    weights = np.ones(n_data)
    solution = np.zeros(n_components + 1)
    for _ in range(_MISFIT_REWEIGHTS):
        weighted = design * weights.reshape((n_data, 1))
        solution = nnls_kernel(weighted, squares * weights)
        if solution[0] > max_noise:
            solution[0] = max_noise
            if n_components > 0:
                solution[1:] = nnls_kernel(
                    np.ascontiguousarray(weighted[:, 1:]),
                    (squares - max_noise * design[:, 0]) * weights,
                )
        expected = np.dot(design, solution)
        floor = 1e-3 * max(expected.mean(), 1e-300)
        for i in range(n_data):
            weights[i] = 1.0 / max(expected[i], floor)
    return solution[0], solution[1:].copy(), dofs


@compiled
def predictive_covariances_kernel(
    inverse: FloatArray,
    data_normal: FloatArray,
    prior_normal: FloatArray,
    error_normals: FloatArray,
    noise: float,
    model_errors: FloatArray,
    dofs: FloatArray,
    blocks: IntArray,
) -> FloatArray:
    """:func:`app.vlp.uncertainty.predictive_covariances` (level 0.95): the parameter pairs
    ``blocks`` (K, 2) of ``A (a J^T J + sum_c b_c J^T F_c F_c^T J + N_prior) A``, widened."""
    n_blocks = blocks.shape[0]
    n_params = inverse.shape[0]
    n_parts = error_normals.shape[0] + 1
    # Only the rows of A that the blocks read: A_b N A_b^T for each part's N.
    picked = np.empty((2 * n_blocks, n_params))
    for i in range(n_blocks):
        for j in range(2):
            picked[2 * i + j] = inverse[blocks[i, j]]
    variances = np.empty(n_parts)
    variances[0] = noise
    variances[1:] = model_errors
    out = np.zeros((n_blocks, 2, 2))
    shares = np.zeros((n_parts, n_blocks))
    for part in range(n_parts + 1):
        if part == 0:
            middle = data_normal
        elif part < n_parts:
            middle = error_normals[part - 1]
        else:
            middle = prior_normal
        product = np.dot(np.dot(picked, middle), picked.T)
        for i in range(n_blocks):
            if part < n_parts:
                shares[part, i] = variances[part] * (
                    product[2 * i, 2 * i] + product[2 * i + 1, 2 * i + 1]
                )
                scale = variances[part]
            else:
                scale = 1.0
            for a in range(2):
                for b in range(2):
                    out[i, a, b] += scale * product[2 * i + a, 2 * i + b]
    quantile = -2.0 * math.log1p(-_LEVEL)
    for i in range(n_blocks):
        spread = 0.0
        for part in range(n_parts):
            if shares[part, i] > 0.0:
                spread += shares[part, i] ** 2 / max(dofs[part], 1e-300)
        if spread > 0.0:
            total = out[i, 0, 0] + out[i, 1, 1]
            dof = total * total / spread
            # No degrees of freedom left in a float: infinitely wide ("anywhere", bounded).
            widen = dof * math.expm1(quantile / dof) / quantile if dof > 0.0 else math.inf
            for a in range(2):
                for b in range(2):
                    out[i, a, b] *= widen
    return out


@compiled
def sandwich_covariances_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
    max_noise: float,
    level: bool,
) -> tuple[FloatArray, float]:
    """``gridless.uncertainty.fit_uncertainty`` at ``theta``: the position covariances (K, 2, 2)
    and the whitened data cost at the optimum (``level``: as
    :func:`misfit_columns_kernel`)."""
    augmented = _augmented(channel, table, white, data, theta, fixed, layout, priors)
    n_params = theta.shape[0]
    n_data = data.shape[0]
    normal = _symmetric_product(augmented[:n_params])
    jacobian = np.ascontiguousarray(augmented[:n_params, :n_data].T)
    residual = augmented[n_params, :n_data].copy()
    columns, sizes = misfit_columns_kernel(channel, table, white, theta, fixed, layout, level)
    inverse, data_normal, prior_normal, error_normals, noise_leverage, error_leverages, spread = (
        misfit_design_kernel(jacobian, normal, columns, sizes)
    )
    noise, model_errors, dofs = fit_misfit_kernel(
        residual, noise_leverage, error_leverages, spread, max_noise
    )
    k = fixed[0].shape[0]
    blocks = np.empty((k, 2), dtype=np.int64)
    for i in range(k):
        blocks[i, 0], blocks[i, 1] = i, k + i
    covariances = predictive_covariances_kernel(
        inverse, data_normal, prior_normal, error_normals, noise, model_errors, dofs, blocks
    )
    cost = 0.0
    for col in range(n_data):
        cost += residual[col] * residual[col]
    return covariances, cost
