"""Compiled evaluation of the ``gridless`` objective, and its model for the compiled
Levenberg-Marquardt loop.

Stand-ins for :meth:`Objective.augmented` / :func:`gram`, :meth:`Objective.residual` and
:meth:`Whitening.from_state` of :mod:`.gridless.model` (their NumPy code is the reference and
documents the model); :class:`FitModel` is the model :func:`.gridless._compiled.lm.lm_kernel`
fits for :func:`.gridless.model.fit_objective` (a whole LM run is one call). Private: callers
validate.

Arguments come as tuples of plain arrays and numbers (:meth:`Objective.compiled_problem`,
:meth:`Objective.compiled_state`):

- ``white``: ``(has_rotation, rotation (M, M), or (0, 0) when has_rotation is False,
  weights (L,), upper (L,), lower (L,), weighted_diag (L,))``
- ``fixed``: what theta does not hold: ``(heights, weights, log_gains (K,), log_scale,
  on_plane, unit)``
- ``layout``: ``(n_axes, weights_at, gains_at, scale_at, n_prior)``, -1 when absent
- ``priors``: ``(log_gain_sd, log_scale_sd, height_sd, height_mean)``
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ...._kernels import compiled, compiled_inline, compiled_reassociating
from ....typing import FloatArray, IntArray
from ..lm import EIG_FLOOR, SIGMA2_FLOOR, SIGMA2_REL_FLOOR, LMSettings
from .channel import ChannelConstants, TableConstants, channel_rows_kernel, inlined_channel_rows
from .lm import lm_kernel, register_model

__all__ = [
    "FitModel",
    "fit_kernel",
    "gram_kernel",
    "residual_kernel",
    "whitened_data_kernel",
    "whitening_kernel",
]

Problem = tuple[Any, ...]


# The evaluation's helpers below (and the channel's rows) are inlined into their callers
# (compiled_inline): the LM loop calls them a few times an iteration with the model's large
# tuples of arrays, and as calls they cost about a sixth of the power model's fits.
@compiled_inline
def _multipliers(theta: FloatArray, fixed: Problem, layout: Problem) -> tuple[bool, FloatArray]:
    heights, weights, log_gains, log_scale, _, unit = fixed
    _, weights_at, gains_at, scale_at, _ = layout
    k = heights.shape[0]
    if weights_at >= 0:
        return True, theta[weights_at : weights_at + k].copy()
    if gains_at < 0 and scale_at < 0 and unit:
        return False, np.ones(k)
    gains = theta[gains_at : gains_at + k] if gains_at >= 0 else log_gains
    scale = theta[scale_at] if scale_at >= 0 else log_scale
    out = np.empty(k)
    for i in range(k):
        out[i] = weights[i] * math.exp(scale + 2.0 * gains[i])
    return True, out


@compiled_inline
def _rows(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
) -> FloatArray:
    """Rotated gains and gradients ``U^T g`` as rows, shape (4, K, M)."""
    heights, _, _, _, on_plane, _ = fixed
    n_axes = layout[0]
    k = heights.shape[0]
    # Views of theta (the channel reads them, a trial's evaluation need not copy them).
    xs = theta[:k]
    ys = theta[k : 2 * k]
    # Fitted heights (three axes) are off the receivers' plane; one call site to inline.
    zs = theta[2 * k : 3 * k].copy() if n_axes == 3 else heights
    rows: FloatArray = inlined_channel_rows(channel, table, xs, ys, zs, on_plane and n_axes != 3)
    has_rotation, rotation = white[0], white[1]
    if has_rotation:
        n_leds = rotation.shape[0]
        rotated = np.dot(rows.reshape(4 * k, n_leds), rotation)
        return np.asarray(rotated.reshape(4, k, n_leds))
    return rows


@compiled
def _prior_residuals(theta: FloatArray, layout: Problem, priors: Problem, k: int) -> FloatArray:
    n_axes, _, gains_at, scale_at, n_prior = layout
    log_gain_sd, log_scale_sd, height_sd, height_mean = priors
    out = np.empty(n_prior)
    at = 0
    if gains_at >= 0:
        for i in range(k):
            out[at] = -theta[gains_at + i] / log_gain_sd
            at += 1
    if scale_at >= 0:
        out[at] = -theta[scale_at] / log_scale_sd
        at += 1
    if n_axes == 3:
        for i in range(k):
            out[at] = -(theta[2 * k + i] - height_mean) / height_sd
            at += 1
    return out


@compiled
def residual_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> FloatArray:
    """:meth:`Objective.residual`: the whitened data residual, then the prior residuals."""
    rows = _rows(channel, table, white, theta, fixed, layout)
    residual: FloatArray = _residual_of_rows(rows, white, data, theta, fixed, layout, priors)
    return residual


@compiled_inline
def _residual_of_rows(
    rows: FloatArray,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> FloatArray:
    """:func:`residual_kernel` from the rotated gains :func:`_rows` gave (the same numbers as
    the last row of :func:`_augmented_of_rows`)."""
    _, _, weights, upper, lower, weighted_diag = white
    k = fixed[0].shape[0]
    scaled, multipliers = _multipliers(theta, fixed, layout)
    n_data = data.shape[0]
    n_prior = layout[4]
    out = np.empty(n_data + n_prior)
    noise = theta[theta.shape[0] - 1]
    for col in range(n_data):
        a, b = upper[col], lower[col]
        model = 0.0
        for i in range(k):
            atom = rows[0, i, a] * rows[0, i, b]
            model += multipliers[i] * atom if scaled else atom
        out[col] = data[col] - model * weights[col] - noise * weighted_diag[col]
    if n_prior:
        out[n_data:] = _prior_residuals(theta, layout, priors, k)
    return out


@compiled
def _augmented(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> FloatArray:
    """:meth:`Objective.augmented`: ``[J | r]^T``, shape (len(theta) + 1, L + n_prior)."""
    rows = _rows(channel, table, white, theta, fixed, layout)
    augmented: FloatArray = _augmented_of_rows(rows, white, data, theta, fixed, layout, priors)
    return augmented


@compiled_inline
def _augmented_of_rows(
    rows: FloatArray,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> FloatArray:
    """:func:`_augmented` from the rotated gains :func:`_rows` gave."""
    _, _, weights, upper, lower, weighted_diag = white
    n_axes, weights_at, gains_at, scale_at, n_prior = layout
    log_gain_sd, log_scale_sd, height_sd, _ = priors
    k = fixed[0].shape[0]
    scaled, multipliers = _multipliers(theta, fixed, layout)
    n_data = data.shape[0]
    n_params = theta.shape[0]
    noise = theta[n_params - 1]
    out = np.zeros((n_params + 1, n_data + n_prior))
    model = np.zeros(n_data)
    # Target by target, so that every row of the result is written in order.
    for i in range(k):
        factor = multipliers[i] if scaled else 1.0
        gains = rows[0, i]
        for col in range(n_data):
            a, b = upper[col], lower[col]
            atom = gains[a] * gains[b]
            model[col] += factor * atom if scaled else atom
        for axis in range(n_axes):
            slopes = rows[1 + axis, i]
            row = out[axis * k + i]
            for col in range(n_data):
                a, b = upper[col], lower[col]
                row[col] = (slopes[a] * gains[b] + gains[a] * slopes[b]) * factor * weights[col]
        if weights_at >= 0:
            row = out[weights_at + i]
            for col in range(n_data):
                row[col] = gains[upper[col]] * gains[lower[col]] * weights[col]
        if gains_at >= 0:
            row = out[gains_at + i]
            for col in range(n_data):
                atom = gains[upper[col]] * gains[lower[col]]
                row[col] = atom * (2.0 * factor) * weights[col]
    for col in range(n_data):
        modelled = model[col] * weights[col]
        if scale_at >= 0:
            out[scale_at, col] = modelled
        out[n_params - 1, col] = weighted_diag[col]
        out[n_params, col] = data[col] - modelled - noise * weighted_diag[col]
    if n_prior:
        out[n_params, n_data:] = _prior_residuals(theta, layout, priors, k)
        column = n_data
        if gains_at >= 0:
            for i in range(k):
                out[gains_at + i, column + i] = 1.0 / log_gain_sd
            column += k
        if scale_at >= 0:
            out[scale_at, column] = 1.0 / log_scale_sd
            column += 1
        if n_axes == 3:
            for i in range(k):
                out[2 * k + i, column + i] = 1.0 / height_sd
    return out


@compiled_reassociating
def _symmetric_product(rows: FloatArray) -> FloatArray:
    """``rows @ rows.T`` (both triangles), four outputs at a time: a few dozen short rows,
    where a BLAS call costs more in overhead than the arithmetic."""
    n, length = rows.shape
    out = np.empty((n, n))
    for i in range(n):
        j = 0
        while j + 3 <= i:
            s0 = s1 = s2 = s3 = 0.0
            for col in range(length):
                x = rows[i, col]
                s0 += x * rows[j, col]
                s1 += x * rows[j + 1, col]
                s2 += x * rows[j + 2, col]
                s3 += x * rows[j + 3, col]
            out[i, j], out[i, j + 1], out[i, j + 2], out[i, j + 3] = s0, s1, s2, s3
            j += 4
        while j <= i:
            total = 0.0
            for col in range(length):
                total += rows[i, col] * rows[j, col]
            out[i, j] = total
            j += 1
        for j in range(i):
            out[j, i] = out[i, j]
    return out


# Sparse products: for rows at least this long whose mean fraction of nonzeros is below
# _SPARSE_DENSITY (a large room: a target's rows reach the few LEDs it sees).
_SPARSE_MIN_LENGTH = 128
_SPARSE_DENSITY = 0.25


@compiled
def _sparse_symmetric_product(rows: FloatArray) -> tuple[FloatArray, bool]:
    """``rows @ rows.T`` over each pair's shorter list of nonzeros, and True; or an empty
    array and False when the rows are too short or too dense for that to pay.

    A large room's Jacobian rows are mostly zeros; skipping them changes a sum only in its
    round-off (the order of the remaining terms), within the tests' 1e-10.
    """
    n, length = rows.shape
    if length < _SPARSE_MIN_LENGTH:
        return np.empty((0, 0)), False
    counts = np.zeros(n, dtype=np.int64)
    for i in range(n):
        for col in range(length):
            if rows[i, col] != 0.0:
                counts[i] += 1
    if counts.sum() >= _SPARSE_DENSITY * n * length:
        return np.empty((0, 0)), False
    starts = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        starts[i + 1] = starts[i] + counts[i]
    columns = np.empty(starts[n], dtype=np.int64)
    for i in range(n):
        at = starts[i]
        for col in range(length):
            if rows[i, col] != 0.0:
                columns[at] = col
                at += 1
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            # Walk the shorter support; skip pairs whose column ranges do not meet.
            short, other = (i, j) if counts[i] <= counts[j] else (j, i)
            if counts[short] == 0:
                continue
            if counts[other] > 0 and (
                columns[starts[short + 1] - 1] < columns[starts[other]]
                or columns[starts[other + 1] - 1] < columns[starts[short]]
            ):
                continue
            total = 0.0
            for at in range(starts[short], starts[short + 1]):
                col = columns[at]
                total += rows[short, col] * rows[other, col]
            out[i, j] = total
            out[j, i] = total
    return out, True


@compiled
def gram_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`gram`: ``J^T J``, ``J^T r`` and ``r^T r`` at ``theta``."""
    rows = _rows(channel, table, white, theta, fixed, layout)
    normal, gradient, cost = _gram_of_rows(rows, white, data, theta, fixed, layout, priors)
    return normal, gradient, float(cost)


@compiled_inline
def _gram_of_rows(
    rows: FloatArray,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    fixed: Problem,
    layout: Problem,
    priors: Problem,
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`gram_kernel` from the rotated gains :func:`_rows` gave."""
    augmented = _augmented_of_rows(rows, white, data, theta, fixed, layout, priors)
    if augmented.shape[1] >= _SPARSE_MIN_LENGTH:
        product, sparse = _sparse_symmetric_product(augmented)
        if not sparse:
            product = _symmetric_product(augmented)
    else:  # too short for the sparse product (which would say so)
        product = _symmetric_product(augmented)
    n = theta.shape[0]
    return product[:n, :n].copy(), product[:n, n].copy(), float(product[n, n])


@compiled_inline
def _one_row_cost(residual: FloatArray) -> float:
    """``r^T r`` to the bit as :func:`_gram_of_rows` gives it where its product is dense and
    ``n + 1`` (n parameters) is not a multiple of four: the ``[n, n]`` entry of
    ``_symmetric_product([J | r]^T)`` is then summed by its one-row loop (which reorders the
    sum in its own way), so the same loop runs here."""
    block = residual.reshape((1, residual.shape[0]))  # a view: the same row, not a copy
    return float(_symmetric_product(block)[0, 0])


class FitModel(NamedTuple):
    """The aggregated fit's model for :func:`.gridless._compiled.lm.lm_kernel`: the
    :meth:`Objective.compiled_problem` and :meth:`Objective.compiled_state` tuples."""

    channel: ChannelConstants
    table: TableConstants
    white: Problem
    data: FloatArray
    fixed: Problem
    layout: Problem
    priors: Problem


# A fit point: the rotated gains (4, K, M), and J^T J and J^T r when they were computed
# with the cost (ready), else empty.
FitPoint = tuple[FloatArray, FloatArray, FloatArray, bool]


@compiled_inline
def fit_evaluate(model: FitModel, theta: FloatArray) -> tuple[float, FitPoint]:
    """The aggregated fit's ``evaluate``: the cost, and as the point the rotated gains, from
    which :func:`fit_normal_equations` builds ``J^T J`` and ``J^T r`` if the trial is
    accepted: the power model's fits (one value per LED) reject about half their trials. The
    same cost to the bit as :func:`gram_kernel`'s. The product is taken with the cost for
    the correlation model, whose more damped fits accept most trials (the cost alone would
    then be computed twice), and where that cost is not summed by the product's one-row
    loop, which :func:`_one_row_cost` runs (a large room's products skip zeros in an order
    that depends on the Jacobian; with ``n + 1`` a multiple of four the four-row loop sums
    it)."""
    channel, table, white, data, fixed, layout, priors = model
    rows = _rows(channel, table, white, theta, fixed, layout)
    if (
        data.shape[0] != rows.shape[2]
        or data.shape[0] + layout[4] >= _SPARSE_MIN_LENGTH
        or (theta.shape[0] + 1) % 4 == 0
    ):
        normal, gradient, cost = _gram_of_rows(rows, white, data, theta, fixed, layout, priors)
        return cost, (rows, normal, gradient, True)
    residual = _residual_of_rows(rows, white, data, theta, fixed, layout, priors)
    return _one_row_cost(residual), (rows, np.empty((0, 0)), np.empty(0), False)


@compiled_inline
def fit_normal_equations(
    model: FitModel, theta: FloatArray, point: FitPoint
) -> tuple[FloatArray, FloatArray]:
    """The aggregated fit's ``normal_equations``: ``J^T J`` and ``J^T r`` at the accepted
    point, from its rotated gains."""
    rows, normal, gradient, ready = point
    if ready:
        return normal, gradient
    _, _, white, data, fixed, layout, priors = model
    normal, gradient, _ = _gram_of_rows(rows, white, data, theta, fixed, layout, priors)
    return normal, gradient


register_model(FitModel, fit_evaluate, fit_normal_equations)


@compiled
def fit_kernel(
    fields: Problem, theta0: FloatArray, lower: FloatArray, upper: FloatArray, settings: Problem
) -> tuple[FloatArray, float, int]:
    """:func:`.gridless._compiled.lm.lm_kernel` on ``FitModel(*fields)`` with
    ``LMSettings(*settings)``: theta, cost and iterations. (Plain tuples cross from Python
    faster than named ones: numba types a named tuple's every field in Python.)"""
    theta, cost, used, _ = lm_kernel(FitModel(*fields), theta0, lower, upper, LMSettings(*settings))
    return theta, cost, used


@compiled
def whitening_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    positions_xy: FloatArray,
    fixed: Problem,
    noise: float,
    n_terminals: float,
    correlation: bool,
    upper: IntArray,
    lower: IntArray,
    is_diag: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:meth:`Whitening.from_state`: the rotation (empty for power) and the weights."""
    heights, _, _, _, on_plane, _ = fixed
    k = heights.shape[0]
    theta = np.empty(2 * k)
    theta[:k] = positions_xy[:, 0]
    theta[k:] = positions_xy[:, 1]
    rows = channel_rows_kernel(
        channel, table, theta[:k].copy(), theta[k:].copy(), heights, on_plane
    )
    gains = rows[0]  # (K, M)
    _, multipliers = _multipliers(theta, fixed, (2, -1, -1, -1, 0))
    n_leds = gains.shape[1]
    count = max(n_terminals, 1.0)
    total = 0.0
    for i in range(k):
        for m in range(n_leds):
            total += gains[i, m] * gains[i, m] * multipliers[i]
    power = total / (n_leds * count)
    sigma2 = max(noise / count, SIGMA2_REL_FLOOR * power, SIGMA2_FLOOR)
    half_noise = 0.5 * count * sigma2
    if not correlation:
        weights = np.empty(n_leds)
        for m in range(n_leds):
            received = 0.0
            for i in range(k):
                received += gains[i, m] * gains[i, m] * multipliers[i]
            weights[m] = 1.0 / math.sqrt(4.0 * sigma2 * (received + half_noise))
        # No rotation (the caller drops it): an empty one, not an M x M identity to fill.
        return np.zeros((0, 0)), weights
    signal = np.zeros((n_leds, n_leds))
    for a in range(n_leds):
        for b in range(n_leds):
            total = 0.0
            for i in range(k):
                total += gains[i, a] * multipliers[i] * gains[i, b]
            signal[a, b] = total
        signal[a, a] += half_noise
    lam, rotation = np.linalg.eigh(signal)
    floor = EIG_FLOOR * max(lam[n_leds - 1], SIGMA2_FLOOR)
    for m in range(n_leds):
        lam[m] = max(lam[m], floor)
    weights = np.empty(upper.shape[0])
    for col in range(upper.shape[0]):
        var = sigma2 * (lam[upper[col]] + lam[lower[col]]) * (1.0 + is_diag[col])
        weights[col] = 1.0 / math.sqrt(var)
    return np.ascontiguousarray(rotation), weights


@compiled
def whitened_data_kernel(white: Problem, values: FloatArray) -> FloatArray:
    """:func:`.gridless.whitening.whitened_data_reference`: ``c * vech(U^T V U)`` of the
    measurement ``vech(V)``."""
    has_rotation, rotation, weights, upper, lower, _ = white
    length = values.shape[0]
    out = np.empty(length)
    if not has_rotation:
        for col in range(length):
            out[col] = weights[col] * values[col]
        return out
    n_leds = rotation.shape[0]
    full = np.zeros((n_leds, n_leds))
    for col in range(length):
        full[upper[col], lower[col]] = values[col]
        full[lower[col], upper[col]] = values[col]
    rotated = np.dot(rotation.T.copy(), np.dot(full, rotation))
    for col in range(length):
        out[col] = weights[col] * rotated[upper[col], lower[col]]
    return out
