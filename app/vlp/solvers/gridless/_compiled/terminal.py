"""Compiled model of one terminal's own fit, and the fit from one start.

Stand-ins for :func:`.gridless.terminals.terminal_model` (all its branches: looking straight up,
a photodiode normal the terminal sent, a fitted tilt) and for the evaluation of
:func:`.gridless.terminals.terminal_fit_reference` (their NumPy code is the reference and documents
the model) as a :class:`TerminalModel` that :func:`.gridless._compiled.lm.lm_kernel` fits; a
whole fit from one start is one call here. Private: callers validate.

Parameters are ``theta = [x, y, (z), (tx, ty), u]``. Arguments beyond the channel's
constants (:func:`.gridless._compiled.channel.channel_constants`):

- ``shape``: ``(free_height, has_normal, free_tilt, z0)``; ``normal`` (3,) is used only with
  ``has_normal``
- ``priors``: ``(with_priors, log_gain_sd, height_mean, height_sd, tilt_sd)``, a standard
  deviation <= 0 meaning "no such prior"
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ...._kernels import compiled, compiled_inline
from ....typing import FloatArray
from ..lm import LMSettings
from .channel import (
    ChannelConstants,
    TableConstants,
    beam_towards,
    channel_fields,
    channel_rows_kernel,
    diffuse_rows,
)
from .lm import lm_kernel, register_model

__all__ = ["TerminalModel", "terminal_fit_kernel", "terminal_model_kernel"]

Shape = tuple[Any, ...]
TerminalPriors = tuple[Any, ...]

# A fit with a gain prior starts its log gain no further from the prior's mean than this many
# prior sds: a start's least-squares gain far out in the prior's tail makes the prior's
# pseudo-residual dwarf the data's, and LM's first steps then move the position wherever
# they reduce it (a gain held at 1 by a tiny sd, started at the least-squares gain, walked
# a terminal from its optimum into a far corner of the room).
START_LOG_GAIN_PRIOR_SDS = 3.0


@compiled
def terminal_model_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    theta: FloatArray,
    shape: Shape,
    normal: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`terminal_model`: gains (M,) and their gradient (M, 5) along x, y, z, tx, ty
    (the tilt's columns zero unless the tilt is free)."""
    free_height, has_normal, free_tilt, z0 = shape
    fields = channel_fields(channel)
    led_x, led_y, led_z = fields[0], fields[1], fields[2]
    free_height_factor, orders, pilot, cos_fov2 = fields[5], fields[6], fields[9], fields[10]
    normals, tilted = fields[12], fields[13]
    beamed = fields[14]
    n_leds = led_x.shape[0]
    x, y = theta[0], theta[1]
    z = theta[2] if free_height else z0
    gradient = np.zeros((n_leds, 5))
    xs, ys, zs = np.array([x]), np.array([y]), np.array([z])
    if not has_normal and not free_tilt:
        rows = channel_rows_kernel(channel, table, xs, ys, zs, False)
        gains = rows[0, 0].copy()
        for m in range(n_leds):
            for axis in range(3):
                gradient[m, axis] = rows[1 + axis, 0, m]
        return gains, gradient
    unit = np.empty(3)
    derivative = np.zeros((3, 2))
    if free_tilt:
        at = 3 if free_height else 2
        tx, ty = theta[at], theta[at + 1]
        length = math.sqrt(tx * tx + ty * ty + 1.0)
        unit[0], unit[1], unit[2] = tx / length, ty / length, 1.0 / length
        for i in range(3):
            for j in range(2):
                identity = 1.0 if i == j else 0.0
                derivative[i, j] = (identity - unit[i] * unit[j]) / length
    else:
        unit[:] = normal
    gains = np.zeros(n_leds)
    for m in range(n_leds):
        ox, oy, oz = led_x[m] - x, led_y[m] - y, led_z[m] - z
        drop = max(oz, 1e-9)
        dist2 = ox * ox + oy * oy + oz * oz
        facing = ox * unit[0] + oy * unit[1] + oz * unit[2]
        if not (facing > 0.0 and facing * facing >= cos_fov2 * dist2):
            continue  # out of view: gain and gradient zero
        order = orders[m]
        gain = (
            free_height_factor[m]
            * math.pow(drop, order)
            * max(facing, 1e-300)
            * math.pow(dist2, -(order + 3.0) / 2.0)
        )
        per_x = 0.0
        per_y = 0.0
        per_z = 0.0
        if tilted[m]:
            emitting = -(ox * normals[m, 0] + oy * normals[m, 1] + oz * normals[m, 2])
            if not emitting > 0.0:
                continue  # behind the LED's face: gain and gradient zero
            gain *= math.pow(emitting / drop, order)
            per_x = order * normals[m, 0] / emitting
            per_y = order * normals[m, 1] / emitting
            per_z = order * (normals[m, 2] / emitting + 1.0 / drop)
        along = (order + 3.0) / dist2
        gradient[m, 0] = gain * (-unit[0] / facing + along * ox + per_x)
        gradient[m, 1] = gain * (-unit[1] / facing + along * oy + per_y)
        gradient[m, 2] = gain * (-(order / drop) - unit[2] / facing + along * oz + per_z)
        if free_tilt:
            along_normal = gain / facing
            for j in range(2):
                gradient[m, 3 + j] = (
                    along_normal * ox * derivative[0, j]
                    + along_normal * oy * derivative[1, j]
                    + along_normal * oz * derivative[2, j]
                )
        if beamed[m]:
            # r - s = -(ox, oy, oz)
            beam, beam_x, beam_y, beam_z = beam_towards(channel, m, -ox, -oy, -oz)
            gradient[m, 0] = gradient[m, 0] * beam + gain * beam_x
            gradient[m, 1] = gradient[m, 1] * beam + gain * beam_y
            gradient[m, 2] = gradient[m, 2] * beam + gain * beam_z
            gradient[m, 3] *= beam
            gradient[m, 4] *= beam
            gain *= beam
        gains[m] = gain
    if table[0] != 0:
        diffuse = diffuse_rows(table, xs, ys, zs, True)
        for m in range(n_leds):
            gains[m] += diffuse[0, 0, m] * pilot[m]
            for axis in range(3):
                gradient[m, axis] += diffuse[1 + axis, 0, m] * pilot[m]
    return gains, gradient


class TerminalModel(NamedTuple):
    """One terminal's fit, the model :func:`.gridless._compiled.lm.lm_kernel` fits for
    :func:`terminal_fit_kernel`."""

    channel: ChannelConstants
    table: TableConstants
    amplitudes: FloatArray
    weights: FloatArray
    shape: Shape
    normal: FloatArray
    priors: TerminalPriors


@compiled_inline
def terminal_evaluate(
    model: TerminalModel, theta: FloatArray
) -> tuple[float, tuple[FloatArray, FloatArray]]:
    """The terminal fit's ``evaluate``: the cost and, as the point, the whitened residual
    (data, then priors) and Jacobian (the reference's ``evaluate``)."""
    channel, table, amplitudes, weights, shape, normal, priors = model
    free_height, _, free_tilt, _ = shape
    with_priors, log_gain_sd, height_mean, height_sd, tilt_sd = priors
    gains, gradient = terminal_model_kernel(channel, table, theta, shape, normal)
    n_data = amplitudes.shape[0]
    n_params = theta.shape[0]
    axes = n_params - 1
    gain_prior = with_priors and log_gain_sd > 0.0
    height_prior = with_priors and free_height
    tilt_prior = with_priors and free_tilt and tilt_sd > 0.0
    n_rows = n_data + int(gain_prior) + int(height_prior) + 2 * int(tilt_prior)
    residual = np.empty(n_rows)
    jacobian = np.zeros((n_rows, n_params))
    amp = math.exp(theta[n_params - 1])
    # The gradient's columns in theta's order: x, y, then z and the tilt when free.
    columns = np.empty(axes, dtype=np.int64)
    columns[0], columns[1] = 0, 1
    at = 2
    if free_height:
        columns[at] = 2
        at += 1
    if free_tilt:
        columns[at], columns[at + 1] = 3, 4
    for m in range(n_data):
        weight = weights[m]
        residual[m] = weight * (amplitudes[m] - amp * gains[m])
        scaled = weight * amp
        for p in range(axes):
            jacobian[m, p] = scaled * gradient[m, columns[p]]
        jacobian[m, n_params - 1] = scaled * gains[m]
    row = n_data
    if gain_prior:
        residual[row] = -theta[n_params - 1] / log_gain_sd
        jacobian[row, n_params - 1] = 1.0 / log_gain_sd
        row += 1
    if height_prior:
        residual[row] = -(theta[2] - height_mean) / height_sd
        jacobian[row, 2] = 1.0 / height_sd
        row += 1
    if tilt_prior:
        tilt_at = 3 if free_height else 2
        for offset in range(2):
            residual[row] = -theta[tilt_at + offset] / tilt_sd
            jacobian[row, tilt_at + offset] = 1.0 / tilt_sd
            row += 1
    return _squared_norm(residual), (residual, jacobian)


@compiled_inline
def terminal_normal_equations(
    _model: TerminalModel, _theta: FloatArray, point: tuple[FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray]:
    """The terminal fit's ``normal_equations``: ``J^T J`` and ``J^T r`` of the point."""
    residual, jacobian = point
    return jacobian.T @ jacobian, jacobian.T @ residual


register_model(TerminalModel, terminal_evaluate, terminal_normal_equations)


@compiled
def _squared_norm(values: FloatArray) -> float:
    total = 0.0
    for value in values:
        total += value * value
    return total


@compiled
def terminal_fit_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    amplitudes: FloatArray,
    weights: FloatArray,
    theta0: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    shape: Shape,
    normal: FloatArray,
    priors: TerminalPriors,
    settings: tuple[Any, ...],
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """One start's fit (the reference's start, then :func:`.gridless._compiled.lm.lm_kernel`
    on a :class:`TerminalModel`): theta, whitened residual, Jacobian and cost at the last
    accepted point. ``theta0``'s last entry (the log gain) is replaced by the least-squares
    gain of the start's gains, within :data:`START_LOG_GAIN_PRIOR_SDS` of a gain prior, as the
    reference starts. ``settings``: the fields of its
    :class:`.gridless.lm.LMSettings` (a plain tuple crosses from Python faster)."""
    free_height, has_normal, _, z0 = shape
    theta = theta0.copy()
    start = np.empty(3)
    start[0], start[1], start[2] = theta[0], theta[1], z0
    # The start's gains: its own normal if sent, else straight up (the tilt starts level).
    start_shape = (free_height, has_normal, False, z0)
    gains0, _ = terminal_model_kernel(channel, table, start, start_shape, normal)
    norm = _squared_norm(gains0)
    if norm > 0.0:
        projection = 0.0
        for m in range(gains0.shape[0]):
            projection += gains0[m] * amplitudes[m]
        theta[theta.shape[0] - 1] = math.log(max(projection / norm, 1e-6))
    else:
        theta[theta.shape[0] - 1] = 0.0
    with_priors, log_gain_sd = priors[0], priors[1]
    if with_priors and log_gain_sd > 0.0:
        reach = START_LOG_GAIN_PRIOR_SDS * log_gain_sd
        theta[theta.shape[0] - 1] = min(max(theta[theta.shape[0] - 1], -reach), reach)
    theta, cost, _, point = lm_kernel(
        TerminalModel(channel, table, amplitudes, weights, shape, normal, priors),
        theta,
        lower,
        upper,
        LMSettings(*settings),
    )
    residual, jacobian = point
    return theta, residual, jacobian, cost
