"""Compiled steps of the ``gridless`` search: an ADCG growth step and whitened refinement.

Stand-ins for :func:`.gridless.search.grow` and :func:`.gridless.search.refine` in dense
rooms with the correlation model during the search (positions and noise only;
:func:`.gridless.search.search_compiles` says when):

- :func:`grow_kernel`: growth steps (:func:`_growth_step`: the plug-in whitening of the
  current state, its whitened residual, the insertion scores of every grid point, the best
  one, away from the points to avoid, and the short Levenberg-Marquardt refinement with
  the new target), one or as many as K targets take;
- :func:`refine_kernel`: rounds of the plug-in whitening of the current state and a
  Levenberg-Marquardt fit in it, until a round barely moves the fit.

Each is one call instead of some sixty Python-level steps. They call the kernels the Python
path calls (:mod:`.gridless._compiled.fit`), in the same order, so the state they return is that
path's to the bit; the Python path (and under ``VLP_KERNELS=reference`` its NumPy kernels)
is their reference. Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from ...._kernels import compiled
from ....typing import FloatArray
from ..lm import MAX_REJECTIONS, LMSettings
from .channel import ChannelConstants, TableConstants
from .fit import (
    FitModel,
    Problem,
    residual_kernel,
    whitened_data_kernel,
    whitening_kernel,
)
from .lm import lm_kernel
from .scores import correlation_scores_kernel

__all__ = ["escape_test_kernel", "grow_kernel", "refine_kernel"]


@compiled
def _facts(
    heights: FloatArray,
    weights: FloatArray,
    log_gains: FloatArray,
    log_scale: float,
    receiver_height: float,
) -> tuple[bool, bool]:
    """Whether every target is on the receivers' plane, and every multiplier is 1
    (:func:`.gridless.model.fixed_tuple`)."""
    on_plane = True
    unit = log_scale == 0.0
    for i in range(heights.shape[0]):
        on_plane = on_plane and heights[i] == receiver_height
        unit = unit and log_gains[i] == 0.0 and weights[i] == 1.0
    return on_plane, unit


@compiled
def _theta(positions: FloatArray, noise: float) -> FloatArray:
    """The search's ``theta = [x_1..x_K, y_1..y_K, s]`` (:meth:`Objective.pack`)."""
    k = positions.shape[0]
    theta = np.empty(2 * k + 1)
    for i in range(k):
        theta[i] = positions[i, 0]
        theta[k + i] = positions[i, 1]
    theta[2 * k] = noise
    return theta


@compiled
def _positions(theta: FloatArray, k: int) -> FloatArray:
    """The positions (K, 2) held by a search ``theta`` (:meth:`Objective.unpack`)."""
    out = np.empty((k, 2))
    for i in range(k):
        out[i, 0] = theta[i]
        out[i, 1] = theta[k + i]
    return out


@compiled
def _clip(theta: FloatArray, lower: FloatArray, upper: FloatArray) -> None:
    """``theta`` within its bounds, in place, when its noise has a ceiling (a state's noise
    may be above an objective's: LM starts within them, as the Python path does)."""
    if upper[theta.shape[0] - 1] < np.inf:
        for i in range(theta.shape[0]):
            theta[i] = min(max(theta[i], lower[i]), upper[i])


@compiled
def _plug_in(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    positions: FloatArray,
    fixed: Problem,
    noise: float,
    is_diag: FloatArray,
) -> Problem:
    """:meth:`Whitening.from_state` (correlation) of a state of K >= 1 targets, as the
    compiled kernels take it; ``white`` lends its vech indices."""
    upper_index, lower_index = white[3], white[4]
    rotation, entry_weights = whitening_kernel(
        channel,
        table,
        positions,
        fixed,
        noise,
        float(positions.shape[0]),
        True,
        upper_index,
        lower_index,
        is_diag,
    )
    weighted_diag = np.empty(entry_weights.shape[0])
    for col in range(entry_weights.shape[0]):
        weighted_diag[col] = entry_weights[col] * is_diag[col]
    return (True, rotation, entry_weights, upper_index, lower_index, weighted_diag)


@compiled
def _growth_step(
    channel: ChannelConstants,
    table: TableConstants,
    search: Problem,
    state: Problem,
    gains: FloatArray,
    centres: FloatArray,
    avoid: FloatArray,
    avoid_radius: float,
    lower: FloatArray,
    upper: FloatArray,
    inner_iter: int,
) -> tuple[FloatArray, float, int]:
    """One growth step of the search's ``state``: the new positions (K + 1, 2), noise
    coefficient and LM iterations used (0 when ``inner_iter`` is 0: inserted, not refined).

    ``search``: ``(white, plug_in, is_diag, values, receiver_height, layout, priors,
    initial_damping, tol, step_tol)``: the step runs in the state's plug-in whitening when
    ``plug_in`` and K > 0 (:meth:`Whitening.from_state`, ``is_diag`` the entries' diagonal
    indicator), else in ``white`` (the plain metric); ``values`` the measurement
    (normalised, not whitened); ``layout``, ``priors`` the search priors' tuples (positions
    and noise only, new targets at the priors' mean height); the LM settings.
    ``state``: ``(positions (K, 2), noise, heights, weights, log_gains (K,), log_scale)``.
    ``gains`` (M, N) and ``centres`` (N, 2): the grid's scaled gains and points; ``avoid``
    (n, 2): points whose ``avoid_radius`` the insertion stays out of, unless that leaves
    none; ``lower``, ``upper``: the bounds of theta for K + 1 targets.
    """
    white, plug_in, is_diag, values, receiver_height, layout, priors = search[:7]
    initial_damping, tol, step_tol = search[7:]
    positions, noise, heights, weights, log_gains, log_scale = state
    height_mean = priors[3]
    k = positions.shape[0]
    if k > 0:
        on_plane, unit = _facts(heights, weights, log_gains, log_scale, receiver_height)
        fixed = (heights, weights, log_gains, log_scale, on_plane, unit)
        if plug_in:
            white = _plug_in(channel, table, white, positions, fixed, noise, is_diag)
    data = whitened_data_kernel(white, values)
    if k == 0:
        residual = data
    else:
        theta = _theta(positions, noise)
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
    grown = np.empty((n, 2))
    grown[:k] = positions
    grown[k] = centres[best]
    theta = _theta(grown, noise)
    used = 0
    if inner_iter > 0:
        _clip(theta, lower, upper)
        on_plane, unit = _facts(
            grown_heights, grown_weights, grown_gains, log_scale, receiver_height
        )
        fixed = (grown_heights, grown_weights, grown_gains, log_scale, on_plane, unit)
        settings = LMSettings(
            inner_iter, initial_damping, MAX_REJECTIONS, tol, step_tol, 2 * n, True
        )
        theta, _, used, _ = lm_kernel(
            FitModel(channel, table, white, data, fixed, layout, priors),
            theta,
            lower,
            upper,
            settings,
        )
    return _positions(theta, n), theta[2 * n], used


@compiled
def _bounds_for(lower: FloatArray, upper: FloatArray, k: int) -> tuple[FloatArray, FloatArray]:
    """The search's bounds of theta for ``k`` targets, from those for more (positions,
    then the noise: each block's bounds are the same for every target)."""
    n = (lower.shape[0] - 1) // 2
    out_lower = np.empty(2 * k + 1)
    out_upper = np.empty(2 * k + 1)
    out_lower[:k] = lower[:k]
    out_upper[:k] = upper[:k]
    out_lower[k : 2 * k] = lower[n : n + k]
    out_upper[k : 2 * k] = upper[n : n + k]
    out_lower[2 * k] = lower[2 * n]
    out_upper[2 * k] = upper[2 * n]
    return out_lower, out_upper


@compiled
def grow_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    search: Problem,
    state: Problem,
    gains: FloatArray,
    centres: FloatArray,
    avoid: FloatArray,
    avoid_radius: float,
    lower: FloatArray,
    upper: FloatArray,
    inner_iter: int,
) -> tuple[FloatArray, float, int, int]:
    """Growth steps (:func:`_growth_step`) from ``state`` until it holds as many
    targets as ``lower`` and ``upper`` bound (2 K + 1 values), the first insertion away
    from ``avoid``. Returns the positions (K, 2), the noise coefficient, the LM iterations of
    all steps and those of the last."""
    positions, noise, heights, weights, log_gains, log_scale = state
    height_mean = search[6][3]
    n_targets = (lower.shape[0] - 1) // 2
    total = 0
    used = 0
    first = True
    nowhere = np.empty((0, 2))
    while positions.shape[0] < n_targets:
        k = positions.shape[0]
        step_lower, step_upper = _bounds_for(lower, upper, k + 1)
        positions, noise, used = _growth_step(
            channel,
            table,
            search,
            (positions, noise, heights, weights, log_gains, log_scale),
            gains,
            centres,
            avoid if first else nowhere,
            avoid_radius,
            step_lower,
            step_upper,
            inner_iter,
        )
        total += used
        first = False
        grown = np.empty(k + 1)
        grown[:k] = heights
        grown[k] = height_mean
        heights = grown
        grown = np.empty(k + 1)
        grown[:k] = weights
        grown[k] = 1.0
        weights = grown
        grown = np.empty(k + 1)
        grown[:k] = log_gains
        grown[k] = 0.0
        log_gains = grown
    return positions, noise, total, used


@compiled
def refine_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    search: Problem,
    state: Problem,
    lower: FloatArray,
    upper: FloatArray,
    rounds: int,
    max_iter: int,
) -> tuple[FloatArray, float, int, int]:
    """Whitened refinement of the search's ``state`` (K >= 1; the tuples of
    :func:`_growth_step`): up to ``rounds`` (at least one) LM fits of positions and
    noise, each in the plug-in whitening of the state the round before left when
    ``plug_in`` (else in ``white``), stopping after a round past the first that used at
    most 2 iterations. Returns the positions (K, 2), the noise coefficient, the iterations
    of all rounds and those of the last."""
    white, plug_in, is_diag, values, receiver_height, layout, priors = search[:7]
    initial_damping, tol, step_tol = search[7:]
    positions, noise, heights, weights, log_gains, log_scale = state
    k = positions.shape[0]
    on_plane, unit = _facts(heights, weights, log_gains, log_scale, receiver_height)
    fixed = (heights, weights, log_gains, log_scale, on_plane, unit)
    theta = _theta(positions, noise)
    current = positions.copy()
    total = 0
    used = 0
    for round_index in range(max(rounds, 1)):
        metric = white
        if plug_in:
            metric = _plug_in(channel, table, white, current, fixed, theta[2 * k], is_diag)
        data = whitened_data_kernel(metric, values)
        _clip(theta, lower, upper)
        settings = LMSettings(max_iter, initial_damping, MAX_REJECTIONS, tol, step_tol, 2 * k, True)
        theta, _, used, _ = lm_kernel(
            FitModel(channel, table, metric, data, fixed, layout, priors),
            theta,
            lower,
            upper,
            settings,
        )
        total += used
        current = _positions(theta, k)
        if round_index > 0 and used <= 2:
            break  # the re-whitened metric no longer moves the fit
    return current, theta[2 * k], total, used


@compiled
def escape_test_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    search: Problem,
    state: Problem,
    gains: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """What the escape test (:func:`.gridless.search.escape_test_reference`) reads of the
    search's ``state`` (K >= 1), in its plug-in whitening: that whitening's rotation and
    weights, the whitened data, the whitened data residual, and every grid point's
    ``<c psi_j, r>`` and ``||c psi_j||^2`` (:func:`.scores.correlation_scores_kernel`)."""
    white, _, is_diag, values, receiver_height, layout, priors = search[:7]
    positions, noise, heights, weights, log_gains, log_scale = state
    on_plane, unit = _facts(heights, weights, log_gains, log_scale, receiver_height)
    fixed = (heights, weights, log_gains, log_scale, on_plane, unit)
    metric = _plug_in(channel, table, white, positions, fixed, noise, is_diag)
    data = whitened_data_kernel(metric, values)
    theta = _theta(positions, noise)
    full = residual_kernel(channel, table, metric, data, theta, fixed, layout, priors)
    residual = full[: data.shape[0]].copy()
    num, norms = correlation_scores_kernel(metric, residual, gains)
    return metric[1], metric[2], data, residual, num, norms
