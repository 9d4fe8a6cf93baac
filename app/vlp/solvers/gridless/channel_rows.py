"""The channel's gains and their x, y, z derivatives at points, as rows ``(4, P, M)``: the
compiled kernel (:func:`._compiled.channel.channel_rows_kernel`) and its NumPy reference
(from :meth:`.channel.ChannelKernel.gradients_xy` and
:meth:`~.channel.ChannelKernel.gradients_xyz`). Private: callers validate.
"""

from __future__ import annotations

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray
from ._compiled import channel as compiled_channel
from .channel import ChannelKernel

__all__ = ["channel_rows", "channel_rows_kernel", "channel_rows_reference"]


def channel_rows(
    kernel: ChannelKernel, xs: FloatArray, ys: FloatArray, zs: FloatArray, on_plane: bool
) -> FloatArray:
    """Rows ``[g, dg/dx, dg/dy, dg/dz]`` of shape (4, P, M) at the points: on the receivers'
    plane with ``on_plane`` (``zs`` ignored, ``dg/dz`` zero), else at heights ``zs``."""
    return dispatch(channel_rows_kernel, channel_rows_reference)(kernel, xs, ys, zs, on_plane)


def channel_rows_kernel(
    kernel: ChannelKernel, xs: FloatArray, ys: FloatArray, zs: FloatArray, on_plane: bool
) -> FloatArray:
    """:func:`channel_rows_reference` in one compiled call (in NumPy for a diffuse table
    without a compiled interpolation)."""
    constants = compiled_channel.channel_constants(kernel)
    if constants is None:
        return channel_rows_reference(kernel, xs, ys, zs, on_plane)
    return np.asarray(
        compiled_channel.channel_rows_kernel(
            *constants,
            np.ascontiguousarray(xs, dtype=np.float64),
            np.ascontiguousarray(ys, dtype=np.float64),
            np.ascontiguousarray(zs, dtype=np.float64),
            on_plane,
        )
    )


def channel_rows_reference(
    kernel: ChannelKernel, xs: FloatArray, ys: FloatArray, zs: FloatArray, on_plane: bool
) -> FloatArray:
    """:func:`channel_rows` in NumPy."""
    n_points = xs.shape[0]
    rows = np.zeros((4, n_points, kernel.n_leds))
    if on_plane:
        blocks = kernel.gradients_xy(xs, ys)  # [dg/dx | dg/dy | g | g]
        order: tuple[int, ...] = (1, 2, 0)
    else:
        blocks = kernel.gradients_xyz(xs, ys, zs)  # [dg/dx | dg/dy | dg/dz | g | g | g]
        order = (1, 2, 3, 0)
    for block, row in enumerate(order):
        rows[row] = blocks[:, block * n_points : (block + 1) * n_points].T
    return rows
