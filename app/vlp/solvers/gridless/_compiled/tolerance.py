"""Compiled gains, residual and Jacobian of the joint fit under the room's tolerances, and
its model for the compiled Levenberg-Marquardt loop.

Stand-ins for :meth:`.gridless.joint_model.JointModel.gains` and
:meth:`~.gridless.joint_model.JointModel.residual_and_jacobian`; their NumPy code is the
reference and documents the model. A 16-LED, 8-target evaluation is a few hundred small NumPy
operations there, bound by their overhead; as a :class:`JointFitModel`,
:func:`.gridless._compiled.lm.lm_kernel` fits it in one call. Private: callers validate.

Arguments come as plain arrays and numbers:

- ``channel``, ``table``: :func:`.gridless._compiled.channel.channel_constants` of the kernel;
- ``theta``: ``[x (K), y (K), u (K), v, a (M), delta (M), t_x (K), t_y (K), s]``, the tilts
  only when ``has_tilts``;
- ``heights`` (K,): the targets' heights;
- ``white``: :meth:`.gridless.model.Whitening.compiled` of a correlation whitening (with a
  rotation);
- ``prior_inverse_sd``: the prior rows' weights, ``1 / sd`` of ``theta[2K : 2K + n]``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ...._kernels import compiled, compiled_inline
from ....typing import FloatArray
from ..lm import LMSettings
from .channel import ChannelConstants, TableConstants, channel_fields, diffuse_rows
from .lm import lapack_cholesky_solve, lm_kernel, register_model

__all__ = [
    "GAINS",
    "ORDER",
    "SLOPE_X",
    "SLOPE_Y",
    "TILT_X",
    "TILT_Y",
    "JointFitModel",
    "joint_evaluate",
    "joint_fit_kernel",
    "joint_gains_kernel",
    "joint_residual_kernel",
]

Problem = tuple[Any, ...]

# Rows of joint_gains_kernel's pieces, each (M, K): the gains (which are also their
# derivative along the log amplitudes), their x and y slopes, their derivative along the
# change of order, along each tilt component.
GAINS, SLOPE_X, SLOPE_Y, ORDER, TILT_X, TILT_Y = range(6)


@compiled
def joint_gains_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    theta: FloatArray,
    heights: FloatArray,
    has_tilts: bool,
) -> tuple[FloatArray, FloatArray]:
    """:meth:`JointModel.gains`: the pieces (6, M, K) (rows named by the module's
    constants) and the multipliers ``e^(v + 2 u)`` (K,)."""
    fields = channel_fields(channel)
    led_x, led_y, led_z = fields[0], fields[1], fields[2]
    free_height_factor, orders, half_exponent = fields[5], fields[6], fields[7]
    pilot, cos_fov2 = fields[9], fields[10]
    k = heights.shape[0]
    n_leds = led_x.shape[0]
    xs = theta[:k].copy()
    ys = theta[k : 2 * k].copy()
    at = 3 * k + 1
    log_scale = theta[3 * k]
    multipliers = np.empty(k)
    for i in range(k):
        multipliers[i] = math.exp(log_scale + 2.0 * theta[2 * k + i])
    tilts = np.zeros((2, k))
    if has_tilts:
        for i in range(k):
            tilts[0, i] = theta[at + 2 * n_leds + i]
            tilts[1, i] = theta[at + 2 * n_leds + k + i]
    # The diffuse part (zeros without reflections) at the targets' heights, (4, K, M).
    diffuse = diffuse_rows(table, xs, ys, heights, True)
    out = np.empty((6, n_leds, k))
    for m in range(n_leds):
        amplitude = math.exp(theta[at + m])
        change = theta[at + n_leds + m]
        order = orders[m]
        for i in range(k):
            ox = led_x[m] - xs[i]
            oy = led_y[m] - ys[i]
            oz = led_z[m] - heights[i]
            drop = max(oz, 1e-9)
            dist2 = ox * ox + oy * oy + oz * oz
            # D^(m+1) d^-(m+3) and cos(phi) = D / d through two logarithms (three powers in
            # the reference: the same numbers to a few ulps).
            log_drop = math.log(drop)
            half_log_dist2 = 0.5 * math.log(dist2)
            log_cos = log_drop - half_log_dist2
            los = 0.0
            if drop * drop >= cos_fov2 * dist2:
                los = free_height_factor[m] * math.exp(
                    (order + 1.0) * log_drop - 2.0 * half_exponent[m] * half_log_dist2
                )
            beam = (order + 1.0 + change) / (order + 1.0) * math.exp(change * log_cos)
            per_tilt = los / drop
            tilt_dot = ox * tilts[0, i] + oy * tilts[1, i]
            out[GAINS, m, i] = amplitude * (
                los * beam + per_tilt * tilt_dot + diffuse[0, i, m] * pilot[m]
            )
            # d g / d(x, y): the nominal slope (line of sight and diffuse) with the beam's
            # and the tilt's corrections (as the reference, term by term).
            along_x = ox / dist2
            along_y = oy / dist2
            slope_x = los * (order + 3.0) * along_x
            slope_y = los * (order + 3.0) * along_y
            extra_x = (
                slope_x * (beam - 1.0)
                + los * beam * (change * along_x)
                - tilts[0, i] / drop * los
                + tilt_dot / drop * slope_x
            )
            extra_y = (
                slope_y * (beam - 1.0)
                + los * beam * (change * along_y)
                - tilts[1, i] / drop * los
                + tilt_dot / drop * slope_y
            )
            out[SLOPE_X, m, i] = amplitude * (slope_x + diffuse[1, i, m] * pilot[m] + extra_x)
            out[SLOPE_Y, m, i] = amplitude * (slope_y + diffuse[2, i, m] * pilot[m] + extra_y)
            out[ORDER, m, i] = amplitude * los * beam * (1.0 / (order + 1.0 + change) + log_cos)
            out[TILT_X, m, i] = amplitude * per_tilt * ox
            out[TILT_Y, m, i] = amplitude * per_tilt * oy
    return out, multipliers


@compiled
def joint_residual_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    heights: FloatArray,
    has_tilts: bool,
    prior_inverse_sd: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:meth:`JointModel.residual_and_jacobian`: the residual ``[data - c mu; prior]``
    (L + n_prior,) and ``J = d(c mu)/d theta`` with the priors' rows (L + n_prior, P)."""
    pieces, multipliers, rotated = _joint_model(channel, table, white, theta, heights, has_tilts)
    residual = _joint_residual(white, data, theta, rotated, multipliers, prior_inverse_sd)
    jacobian = _joint_jacobian(
        white, data.shape[0], theta, pieces, rotated, multipliers, prior_inverse_sd
    )
    return residual, jacobian


@compiled
def _joint_model(
    channel: ChannelConstants,
    table: TableConstants,
    white: Problem,
    theta: FloatArray,
    heights: FloatArray,
    has_tilts: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The pieces and multipliers of :func:`joint_gains_kernel` and the pieces the residual
    and the Jacobian need in the whitening's basis: ``U^T`` of the gains and of the
    per-target directions, each (M', K), rows 0 gains, 1-2 slopes, 3-4 tilts."""
    pieces, multipliers = joint_gains_kernel(channel, table, theta, heights, has_tilts)
    rotation = white[1]
    k = heights.shape[0]
    n_leds = rotation.shape[0]
    sources = (GAINS, SLOPE_X, SLOPE_Y, TILT_X, TILT_Y)
    n_rotated = 5 if has_tilts else 3
    rotated = np.zeros((n_rotated, n_leds, k))
    for r in range(n_rotated):
        piece = pieces[sources[r]]
        for m in range(n_leds):
            for a in range(n_leds):
                factor = rotation[m, a]
                for i in range(k):
                    rotated[r, a, i] += factor * piece[m, i]
    return pieces, multipliers, rotated


@compiled
def _joint_residual(
    white: Problem,
    data: FloatArray,
    theta: FloatArray,
    rotated: FloatArray,
    multipliers: FloatArray,
    prior_inverse_sd: FloatArray,
) -> FloatArray:
    """The residual of :func:`joint_residual_kernel` from :func:`_joint_model`'s pieces:
    what a trial step needs to be accepted or rejected."""
    weights, upper, lower = white[2], white[3], white[4]
    k = multipliers.shape[0]
    n_data = data.shape[0]
    n_prior = prior_inverse_sd.shape[0]
    noise = theta[theta.shape[0] - 1]
    residual = np.empty(n_data + n_prior)
    for col in range(n_data):
        a, b = upper[col], lower[col]
        modelled = 0.0
        for i in range(k):
            atom = rotated[0, a, i] * rotated[0, b, i]
            modelled += atom * multipliers[i]
        diagonal = 1.0 if a == b else 0.0
        residual[col] = data[col] - weights[col] * (modelled + noise * diagonal)
    for j in range(n_prior):
        residual[n_data + j] = -theta[2 * k + j] * prior_inverse_sd[j]
    return residual


@compiled
def _joint_jacobian(
    white: Problem,
    n_data: int,
    theta: FloatArray,
    pieces: FloatArray,
    rotated: FloatArray,
    multipliers: FloatArray,
    prior_inverse_sd: FloatArray,
) -> FloatArray:
    """The Jacobian of :func:`joint_residual_kernel` (``n_data`` rows of data) from
    :func:`_joint_model`'s pieces."""
    rotation, weights, upper, lower = white[1], white[2], white[3], white[4]
    k = multipliers.shape[0]
    n_leds = rotation.shape[0]
    n_params = theta.shape[0]
    n_prior = prior_inverse_sd.shape[0]
    n_rotated = rotated.shape[0]
    # Per LED: Q[c, a, i] = sum_k D_c[i, k] mult_k (U^T g)[a, k], D_0 the gains (the log
    # amplitude's direction), D_1 the order part; U^T as rows (contiguous along LEDs).
    transposed = np.ascontiguousarray(rotation.T)
    q = np.zeros((2, n_leds, n_leds))
    for c in range(2):
        piece = pieces[GAINS if c == 0 else ORDER]
        for a in range(n_leds):
            for i in range(n_leds):
                total = 0.0
                for t in range(k):
                    total += piece[i, t] * multipliers[t] * rotated[0, a, t]
                q[c, a, i] = total
    jacobian = np.zeros((n_data + n_prior, n_params))
    amps_at = 3 * k + 1
    tilts_at = amps_at + 2 * n_leds
    for col in range(n_data):
        a, b = upper[col], lower[col]
        w = weights[col]
        row = jacobian[col]
        modelled = 0.0
        for i in range(k):
            atom = rotated[0, a, i] * rotated[0, b, i]
            modelled += atom * multipliers[i]
            row[2 * k + i] = 2.0 * w * atom * multipliers[i]
        # d/dx, d/dy (and d/dt_x, d/dt_y): w ((U^T D)_a (U^T g)_b + (a <-> b)) c_k.
        for r in range(1, n_rotated):
            start = (r - 1) * k if r < 3 else tilts_at + (r - 3) * k
            for i in range(k):
                row[start + i] = (
                    w
                    * (rotated[r, a, i] * rotated[0, b, i] + rotated[0, a, i] * rotated[r, b, i])
                    * multipliers[i]
                )
        row[3 * k] = w * modelled
        # LED i's parameters: w (U[i, a] Q[i, b] + U[i, b] Q[i, a]).
        for c in range(2):
            start = amps_at + c * n_leds
            for i in range(n_leds):
                row[start + i] = w * (transposed[a, i] * q[c, b, i] + transposed[b, i] * q[c, a, i])
        diagonal = 1.0 if a == b else 0.0
        row[n_params - 1] = w * diagonal
    for j in range(n_prior):
        jacobian[n_data + j, 2 * k + j] = prior_inverse_sd[j]
    return jacobian


@compiled
def _normal_equations(
    residual: FloatArray,
    jacobian: FloatArray,
    n_data: int,
    prior_at: int,
    prior_inverse_sd: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """``J^T J`` and ``J^T r``: the data rows by BLAS, the priors' one-hot rows added to
    the diagonal."""
    rows = jacobian[:n_data]
    transposed = np.ascontiguousarray(rows.T)
    normal = np.dot(transposed, rows)
    gradient = np.dot(transposed, residual[:n_data].copy())
    for j in range(prior_inverse_sd.shape[0]):
        weight = prior_inverse_sd[j]
        normal[prior_at + j, prior_at + j] += weight * weight
        gradient[prior_at + j] += weight * residual[n_data + j]
    return normal, gradient


class JointFitModel(NamedTuple):
    """The joint fit, as :func:`.gridless._compiled.lm.lm_kernel` fits it (``data``
    whitened by ``white``)."""

    channel: ChannelConstants
    table: TableConstants
    white: Problem
    data: FloatArray
    heights: FloatArray
    has_tilts: bool
    prior_inverse_sd: FloatArray


@compiled_inline
def joint_evaluate(model: JointFitModel, theta: FloatArray) -> tuple[float, Problem]:
    """The joint fit's ``evaluate``: the cost and, as the point, :func:`_joint_model`'s
    pieces and the residual (the Jacobian waits for :func:`joint_normal_equations`: about
    half of the trials are rejected)."""
    channel, table, white, data, heights, has_tilts, prior_inverse_sd = model
    pieces, multipliers, rotated = _joint_model(channel, table, white, theta, heights, has_tilts)
    residual = _joint_residual(white, data, theta, rotated, multipliers, prior_inverse_sd)
    return np.dot(residual, residual), (pieces, multipliers, rotated, residual)


@compiled_inline
def joint_normal_equations(
    model: JointFitModel, theta: FloatArray, point: Problem
) -> tuple[FloatArray, FloatArray]:
    """The joint fit's ``normal_equations``: the Jacobian at the point, then ``J^T J`` and
    ``J^T r``."""
    _, _, white, data, heights, _, prior_inverse_sd = model
    pieces, multipliers, rotated, residual = point
    n_data = data.shape[0]
    jacobian = _joint_jacobian(white, n_data, theta, pieces, rotated, multipliers, prior_inverse_sd)
    normal, gradient = _normal_equations(
        residual, jacobian, n_data, 2 * heights.shape[0], prior_inverse_sd
    )
    return normal, gradient


register_model(JointFitModel, joint_evaluate, joint_normal_equations, lapack_cholesky_solve)


@compiled
def joint_fit_kernel(
    fields: Problem, theta0: FloatArray, lower: FloatArray, upper: FloatArray, settings: Problem
) -> tuple[FloatArray, float]:
    """:func:`.gridless._compiled.lm.lm_kernel` on ``JointFitModel(*fields)`` with
    ``LMSettings(*settings)``: theta and cost (plain tuples cross from Python faster)."""
    theta, cost, _, _ = lm_kernel(
        JointFitModel(*fields), theta0, lower, upper, LMSettings(*settings)
    )
    return theta, cost
