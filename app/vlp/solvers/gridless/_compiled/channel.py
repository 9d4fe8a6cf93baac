"""Compiled channel: line of sight plus interpolated diffuse reflections, with gradients.

Stands in for :meth:`ChannelKernel.gradients_xy` / :meth:`ChannelKernel.gradients_xyz` and
:meth:`app.vlp.ReflectionTable.evaluate` (their NumPy code is the reference; the formulas are
documented there). Results come as rows, one per point: ``out[0]`` the gains ``g``,
``out[1..3]`` their derivatives along x, y, z, each of shape (P, M). Private: callers validate.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ...._kernels import compiled, compiled_inline
from ...._reflection_table import _UNIT_BASIS, ReflectionTable
from ....typing import FloatArray
from ..channel import ChannelKernel, DiffuseTable

__all__ = [
    "ChannelConstants",
    "TableConstants",
    "beam_at",
    "beam_towards",
    "channel_constants",
    "channel_fields",
    "channel_rows_kernel",
    "inlined_channel_rows",
    "whole_power",
]

# (per LED (10, M): led_x, led_y, led_z, dz2, factor, free_height_factor, orders,
#  half_exponent, max_d2, pilot_over_scale; cos_fov2, receiver_height, normals (M, 3),
#  flags (2, M) bool: tilted, beamed; beam tables (3, M, W): knots, values, slopes (BeamArrays);
#  beam counts (M,) int). Few arrays: a compiled call from Python unboxes each array of its
#  arguments (about 0.15 us apiece, measured); :func:`channel_fields` gives the columns.
ChannelConstants = tuple[Any, ...]
# (n_axes A (0: no reflections), floats: lows (A), highs (A), shifts (A), then the nodes;
#  scales, ints: strides (A), then the offsets; coefficients (rows, M), receiver_height)
TableConstants = tuple[Any, ...]

_UNIT = np.ascontiguousarray(_UNIT_BASIS)


def _floats(values: object) -> FloatArray:
    return np.array(values, dtype=np.float64, order="C", copy=True).ravel()


def _table_constants(table: DiffuseTable | None, n_leds: int) -> TableConstants | None:
    """The table's interpolation plan as plain arrays; None when it is not a
    :class:`ReflectionTable` (the caller then keeps the reference path)."""
    if table is None:
        empty = np.zeros(1)
        return (
            0,
            empty,
            np.zeros((1, 8)),
            np.zeros(1, dtype=np.int64),
            np.zeros((1, n_leds)),
            0.0,
        )
    if not isinstance(table, ReflectionTable):
        return None
    plan = table._plan
    return (
        3 if table.has_heights else 2,
        np.concatenate(
            (_floats(plan.lows), _floats(plan.highs), _floats(plan.shifts), _floats(plan.nodes))
        ),
        np.ascontiguousarray(plan.scales, dtype=np.float64),
        np.concatenate(
            (
                np.array(plan.strides, dtype=np.int64).ravel(),
                np.array(plan.offsets, dtype=np.int64).ravel(),
            )
        ),
        np.ascontiguousarray(table.coefficients.reshape(-1, table.n_leds), dtype=np.float64),
        float(table.receiver_height),
    )


def channel_constants(kernel: ChannelKernel) -> tuple[ChannelConstants, TableConstants] | None:
    """The kernel's constants for :func:`channel_rows_kernel` (built once, kept on the kernel);
    None when its diffuse table has no compiled interpolation."""
    cached: tuple[ChannelConstants, TableConstants] | None = getattr(kernel, "_compiled", None)
    if cached is not None:
        return cached
    table = _table_constants(kernel.diffuse, kernel.n_leds)
    if table is None:
        return None
    beams = kernel.beams
    channel = (
        np.vstack(
            [
                _floats(column)
                for column in (
                    kernel.led_xy[:, 0],
                    kernel.led_xy[:, 1],
                    kernel.led_z,
                    kernel.dz2,
                    kernel.factor,
                    kernel.free_height_factor,
                    kernel.orders,
                    kernel.half_exponent,
                    kernel.max_d2,
                    kernel.pilot_over_scale,
                )
            ]
        ),
        float(kernel.cos_fov2),
        float(kernel.receiver_height),
        np.ascontiguousarray(kernel.normals, dtype=np.float64),
        np.vstack(
            (
                [bool(n[2] != -1.0 or n[0] != 0.0 or n[1] != 0.0) for n in kernel.normals],
                np.asarray(beams.beamed, dtype=np.bool_),
            )
        ),
        np.ascontiguousarray(np.stack((beams.knots, beams.values, beams.slopes)), dtype=np.float64),
        np.ascontiguousarray(beams.counts, dtype=np.int64),
    )
    kernel._compiled = (channel, table)  # type: ignore[attr-defined]
    return channel, table


@compiled_inline
def channel_fields(channel: ChannelConstants) -> tuple[Any, ...]:
    """The channel's columns, each its own array (views of :func:`channel_constants`'s few):
    ``(led_x, led_y, led_z, dz2, factor, free_height_factor, orders, half_exponent, max_d2,
    pilot_over_scale, cos_fov2, receiver_height, normals, tilted, beamed, knots, values,
    slopes, counts)``."""
    per_led, cos_fov2, receiver_height, normals, flags, beams, counts = channel
    return (
        per_led[0],
        per_led[1],
        per_led[2],
        per_led[3],
        per_led[4],
        per_led[5],
        per_led[6],
        per_led[7],
        per_led[8],
        per_led[9],
        cos_fov2,
        receiver_height,
        normals,
        flags[0],
        flags[1],
        beams[0],
        beams[1],
        beams[2],
        counts,
    )


# Whole exponents up to this size are taken by multiplication (:func:`whole_power`).
_MAX_WHOLE_EXPONENT = 4.0


@compiled
def whole_power(base: float, exponent: float) -> float:
    """``base ** exponent`` for a positive ``base``: by repeated multiplication when the
    exponent is whole and at most :data:`_MAX_WHOLE_EXPONENT` in size (the Lambertian orders
    1, 3 and 5 give the channel's -2, -3 and -4, and m + 1 = 2), else ``math.pow``.

    ``math.pow`` is most of a gain's cost (about four fifths of a pair's, measured); a
    product and a division take a fraction of that, within an ulp or two of it (round-off,
    well within the 1e-10 the tests allow)."""
    size = abs(exponent)
    if size > _MAX_WHOLE_EXPONENT or size != math.floor(size):
        return math.pow(base, exponent)
    product = 1.0
    for _ in range(int(size)):
        product *= base
    return 1.0 / product if exponent < 0.0 else product


@compiled
def beam_at(
    knots: FloatArray, values: FloatArray, slopes: FloatArray, count: int, cosine: float
) -> tuple[float, float]:
    """One beam's intensity ``I(c)`` and ``dI/dc`` (:func:`app.vlp.beams.evaluate_beams`:
    the cubic Hermite interpolant on the last ``count`` knots of the padded row)."""
    start = knots.shape[0] - count
    c = min(cosine, 1.0)
    if c < knots[start]:
        return 0.0, 0.0
    cell = start
    while cell < knots.shape[0] - 2 and knots[cell + 1] <= c:
        cell += 1
    h = knots[cell + 1] - knots[cell]
    t = (c - knots[cell]) / h
    y0, y1 = values[cell], values[cell + 1]
    m0, m1 = slopes[cell] * h, slopes[cell + 1] * h
    t2 = t * t
    t3 = t2 * t
    value = (2.0 * t3 - 3.0 * t2 + 1.0) * y0 + (t3 - 2.0 * t2 + t) * m0
    value += (-2.0 * t3 + 3.0 * t2) * y1 + (t3 - t2) * m1
    derivative = ((6.0 * t2 - 6.0 * t) * y0 + (3.0 * t2 - 4.0 * t + 1.0) * m0) / h
    derivative += ((-6.0 * t2 + 6.0 * t) * y1 + (3.0 * t2 - 2.0 * t) * m1) / h
    return max(value, 0.0), derivative


@compiled
def beam_towards(
    channel: ChannelConstants, m: int, ux: float, uy: float, uz: float
) -> tuple[float, float, float, float]:
    """LED ``m``'s beam ``I(c)`` towards a receiver at ``r - s = (ux, uy, uz)`` and its
    derivatives along the receiver's x, y, z: ``I'(c) (n / d - c (r - s) / d^2)`` with
    ``c = n . (r - s) / d`` (:meth:`ChannelKernel.beam_towards`)."""
    fields = channel_fields(channel)
    normals = fields[12]
    nx, ny, nz = normals[m, 0], normals[m, 1], normals[m, 2]
    dist = math.sqrt(ux * ux + uy * uy + uz * uz)
    c = (nx * ux + ny * uy + nz * uz) / dist
    beam, slope = beam_at(fields[15][m], fields[16][m], fields[17][m], fields[18][m], c)
    slope /= dist
    return (
        beam,
        slope * (nx - c * ux / dist),
        slope * (ny - c * uy / dist),
        slope * (nz - c * uz / dist),
    )


@compiled
def diffuse_rows(
    table: TableConstants, xs: FloatArray, ys: FloatArray, zs: FloatArray, given_z: bool
) -> FloatArray:
    """Interpolated diffuse gains and their x, y, z derivatives, shape (4, P, M).

    ``zs`` is used only when ``given_z`` (else the table's receiver height); a single-height
    table has d/dz = 0. Zeros without a table.
    """
    n_axes, floats, scales, ints, coefficients, height = table
    lows, highs = floats[:n_axes], floats[n_axes : 2 * n_axes]
    shifts, nodes = floats[2 * n_axes : 3 * n_axes], floats[3 * n_axes :]
    strides, offsets = ints[:n_axes], ints[n_axes:]
    n_points = xs.shape[0]
    n_leds = coefficients.shape[1]
    out = np.zeros((4, n_points, n_leds))
    if n_axes == 0:
        return out
    basis = np.empty((n_axes, 2, 4))
    cells = np.empty(n_axes, dtype=np.int64)
    n_terms = 4**n_axes
    for p in range(n_points):
        for a in range(n_axes):
            if a == 0:
                coord = xs[p]
            elif a == 1:
                coord = ys[p]
            else:
                coord = zs[p] if given_z else height
            coord = min(max(coord, lows[a]), highs[a]) + shifts[a]
            cell = np.searchsorted(nodes, coord, side="right") - 1
            low = nodes[cell]
            t = (coord - low) / (nodes[cell + 1] - low)
            t2 = t * t
            t3 = t2 * t
            for column in range(8):
                value = (
                    _UNIT[0, column]
                    + t * _UNIT[1, column]
                    + t2 * _UNIT[2, column]
                    + t3 * _UNIT[3, column]
                )
                basis[a, column // 4, column % 4] = value * scales[cell, column]
            cells[a] = cell
        base = 0
        for a in range(n_axes):
            base += strides[a] * cells[a]
        # Output 0: the value; output 1 + a: the derivative along axis a.
        for output in range(n_axes + 1):
            for j in range(n_terms):
                weight = 1.0
                rest = j
                for a in range(n_axes - 1, -1, -1):
                    digit = rest % 4
                    rest //= 4
                    weight *= basis[a, 1 if output == a + 1 else 0, digit]
                row = base + offsets[j]
                for m in range(n_leds):
                    out[output, p, m] += weight * coefficients[row, m]
    return out


@compiled
def channel_rows_kernel(
    channel: ChannelConstants,
    table: TableConstants,
    xs: FloatArray,
    ys: FloatArray,
    zs: FloatArray,
    on_plane: bool,
) -> FloatArray:
    """Gains and their x, y, z derivatives at the points, shape (4, P, M).

    ``on_plane``: receivers at the layout's height (``zs`` ignored, d/dz not computed, as
    :meth:`ChannelKernel.gradients_xy`); else at heights ``zs``
    (:meth:`ChannelKernel.gradients_xyz`).
    """
    rows: FloatArray = inlined_channel_rows(channel, table, xs, ys, zs, on_plane)
    return rows


@compiled_inline
def inlined_channel_rows(
    channel: ChannelConstants,
    table: TableConstants,
    xs: FloatArray,
    ys: FloatArray,
    zs: FloatArray,
    on_plane: bool,
) -> FloatArray:
    """:func:`channel_rows_kernel`, inlined into its compiled caller: the aggregated fit's
    evaluations, a few an LM iteration, would pass the channel's and the table's tuples of
    arrays to a call."""
    (
        led_x,
        led_y,
        led_z,
        dz2,
        factor,
        free_height_factor,
        orders,
        half_exponent,
        max_d2,
        pilot,
        cos_fov2,
        _,
        normals,
        tilted,
        beamed,
        _,
        _,
        _,
        _,
    ) = channel_fields(channel)
    n_points = xs.shape[0]
    n_leds = led_x.shape[0]
    out = np.zeros((4, n_points, n_leds))
    for p in range(n_points):
        for m in range(n_leds):
            dx = xs[p] - led_x[m]
            dy = ys[p] - led_y[m]
            if on_plane:
                d2 = dx * dx
                d2 += dy * dy
                d2 += dz2[m]
                if d2 > max_d2[m]:
                    continue  # out of view: zeros (most LEDs of a large room)
                gain = whole_power(d2, -half_exponent[m]) * factor[m]
                if not d2 <= max_d2[m]:
                    gain = 0.0
                per_x = 0.0
                per_y = 0.0
                if tilted[m]:
                    drop = math.sqrt(dz2[m])
                    facing = normals[m, 0] * dx + normals[m, 1] * dy - normals[m, 2] * drop
                    if not facing > 0.0:
                        continue  # behind the LED's face: zeros
                    gain *= whole_power(facing / drop, orders[m])
                    per_x = orders[m] * normals[m, 0] / facing
                    per_y = orders[m] * normals[m, 1] / facing
                slope = -2.0 * half_exponent[m] * gain / d2
                along_x = slope * dx + gain * per_x
                along_y = slope * dy + gain * per_y
                if beamed[m]:
                    beam, beam_x, beam_y, _ = beam_towards(channel, m, dx, dy, -math.sqrt(dz2[m]))
                    along_x = along_x * beam + gain * beam_x
                    along_y = along_y * beam + gain * beam_y
                    gain *= beam
                out[0, p, m] = gain
                out[1, p, m] = along_x
                out[2, p, m] = along_y
            else:
                drop = max(led_z[m] - zs[p], 1e-9)
                d2 = dx * dx + dy * dy + drop * drop
                if drop * drop < cos_fov2 * d2:
                    continue  # out of view: zeros
                gain = whole_power(d2, -half_exponent[m])
                gain *= whole_power(drop, orders[m] + 1.0)
                gain *= free_height_factor[m]
                if not drop * drop >= cos_fov2 * d2:
                    gain = 0.0
                per_x = 0.0
                per_y = 0.0
                per_z = 0.0
                if tilted[m]:
                    facing = normals[m, 0] * dx + normals[m, 1] * dy - normals[m, 2] * drop
                    if not facing > 0.0:
                        continue  # behind the LED's face: zeros
                    gain *= whole_power(facing / drop, orders[m])
                    per_x = orders[m] * normals[m, 0] / facing
                    per_y = orders[m] * normals[m, 1] / facing
                    per_z = orders[m] * (normals[m, 2] / facing + 1.0 / drop)
                slope = -(orders[m] + 3.0) * gain / d2
                along_x = slope * dx + gain * per_x
                along_y = slope * dy + gain * per_y
                along_z = (
                    gain * ((orders[m] + 3.0) * drop / d2 - (orders[m] + 1.0) / drop) + gain * per_z
                )
                if beamed[m]:
                    beam, beam_x, beam_y, beam_z = beam_towards(channel, m, dx, dy, -drop)
                    along_x = along_x * beam + gain * beam_x
                    along_y = along_y * beam + gain * beam_y
                    along_z = along_z * beam + gain * beam_z
                    gain *= beam
                out[0, p, m] = gain
                out[1, p, m] = along_x
                out[2, p, m] = along_y
                out[3, p, m] = along_z
    if table[0] != 0:
        diffuse = diffuse_rows(table, xs, ys, zs, not on_plane)
        last = 3 if on_plane else 4
        for q in range(last):
            for p in range(n_points):
                for m in range(n_leds):
                    out[q, p, m] += diffuse[q, p, m] * pilot[m]
    return out
