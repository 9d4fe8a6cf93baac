"""Fast evaluation of the normalised channel and its gradients for the continuous solvers.

``g(p) = x * (h_los(p) + h_diffuse(p)) / scale``: the line-of-sight Lambertian gain of every
LED at a receiver looking straight up at ``p = (x, y, z)``, plus the diffuse reflections when
the layout has a reflectance (interpolated from a :class:`DiffuseTable`), times the pilot
amplitudes, divided by the solver's ``scale``. Private: callers validate.

A tilted LED (layout ``normal`` ``n``) multiplies its straight-down line of sight by
``(c / D)^m``, ``c = n . (r - s)``, ``D = z_led - z`` (:mod:`app.vlp.channel`); the gradient
then gains ``m n_x / c``, ``m n_y / c`` and ``m (n_z / c + 1 / D)`` times the gain along x, y
and z. For LEDs pointing down these are exactly 1 and 0, and a layout without tilted LEDs
never computes them.

An LED with a tabulated beam (:mod:`app.vlp.beams`) has order 0 here and its gain is then
multiplied by ``I(c)``, ``c = n . (r - s) / d``; its gradient gains ``h I'(c) dc/dr`` with
``dc/dr = n / d - c (r - s) / d^2`` (:mod:`app.vlp.channel`). A layout without beams never
computes them.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from ...beams import beam_arrays, evaluate_beams
from ...channel import led_constants
from ...layout import Layout
from ...typing import FloatArray

__all__ = ["ChannelKernel", "DiffuseTable"]


class DiffuseTable(Protocol):
    """What the kernel needs of an interpolated diffuse-reflection table."""

    def evaluate(
        self, xs: FloatArray, ys: FloatArray, zs: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Gains ``(M, P)`` and their derivatives along x, y, z at the points."""
        ...


class ChannelKernel:
    """Normalised scaled gains ``g(p) = x * h(p) / scale`` and their position gradients.

    Parameters
    ----------
    layout : Layout
    scale : float
        Divisor of the gains.
    diffuse : DiffuseTable, default=None
        Interpolated diffuse reflections (upward receivers), added to the line of sight.
    """

    def __init__(self, layout: Layout, scale: float, diffuse: DiffuseTable | None = None) -> None:
        orders, prefactors = led_constants(layout)
        leds = layout.led_positions
        self.n_leds = layout.n_leds
        self.diffuse = diffuse
        self.receiver_height = layout.grid.receiver_height
        self.led_xy = np.ascontiguousarray(leds[:, :2])
        self.led_xyz = np.ascontiguousarray(leds)
        self.led_z = leds[:, 2].copy()
        self.dz2 = (leds[:, 2] - layout.grid.receiver_height) ** 2
        self.orders = orders
        self.pilot_over_scale = layout.pilot_amplitudes / scale
        # h = pref * dz^(m+1) / d^(m+3); fold dz^(m+1), the pilot and 1/scale into one factor.
        dz = np.sqrt(self.dz2)
        self.factor = prefactors * dz ** (orders + 1.0) * self.pilot_over_scale
        self.free_height_factor = prefactors * self.pilot_over_scale
        self.half_exponent = 0.5 * (orders + 3.0)
        # In view when dz / d >= cos(FOV), i.e. d^2 <= dz^2 / cos^2(FOV).
        cos_fov = math.cos(math.radians(layout.receiver.fov_deg))
        self.cos_fov2 = max(cos_fov, 0.0) ** 2 * (1.0 - 1e-12)
        self.max_d2 = self.dz2 / max(cos_fov, 1e-300) ** 2 * (1.0 + 1e-12)
        self.bounds = np.array([layout.room.length, layout.room.width])
        self.normals = np.ascontiguousarray(layout.led_normals)
        self.has_tilt = layout.has_tilted_leds
        self.beams = beam_arrays(layout.beams)
        self.has_beams = layout.has_beams
        self._normal_x = self.normals[:, :1]
        self._normal_y = self.normals[:, 1:2]
        self._normal_z = self.normals[:, 2:]
        self._orders = orders[:, None]
        # Column vectors (M, 1) for broadcasting against (M, P) in the hot path.
        self._led_x = self.led_xy[:, :1]
        self._led_y = self.led_xy[:, 1:]
        self._led_z = self.led_z[:, None]
        self._dz2 = self.dz2[:, None]
        self._factor = self.factor[:, None]
        self._free_height_factor = self.free_height_factor[:, None]
        self._orders_plus_one = (orders + 1.0)[:, None]
        self._orders_plus_three = (orders + 3.0)[:, None]
        self._minus_half_exponent = -self.half_exponent[:, None]
        self._minus_twice_half_exponent = -2.0 * self.half_exponent[:, None]
        self._max_d2 = self.max_d2[:, None]
        self._pilot_over_scale = self.pilot_over_scale[:, None]

    def stacked(self, points: FloatArray, with_gradients: bool) -> FloatArray:
        """Columns ``[g | dg/dx | dg/dy]`` of shape (M, 3P), or ``g`` alone (M, P)."""
        n_points = points.shape[0]
        if not with_gradients:
            return self.gains_xy(points[:, 0], points[:, 1])
        blocks = self.gradients_xy(points[:, 0], points[:, 1])
        return np.concatenate(
            [blocks[:, 2 * n_points : 3 * n_points], blocks[:, : 2 * n_points]], axis=1
        )

    def gains_xy(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """``g`` at the points ``(xs, ys)`` (shapes (P,)) on the receivers' plane, (M, P)."""
        dx, dy, d2 = self._distances_squared(xs, ys)
        gains = np.power(d2, self._minus_half_exponent)
        gains *= self._factor
        gains *= d2 <= self._max_d2
        if self.has_tilt:
            gains *= self._tilt(dx, dy, np.sqrt(self._dz2))[0]
        if self.has_beams:
            gains *= self._beam(dx, dy, np.sqrt(self._dz2), d2)[0]
        if self.diffuse is not None:
            gains += self.diffuse.evaluate(xs, ys)[0] * self._pilot_over_scale
        return gains

    def gradients_xy(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """Columns ``[dg/dx | dg/dy | g | g]`` of shape (M, 4P) at the points ``(xs, ys)``.

        The order suits the objective: the gains twice, next to both gradient blocks, make
        the product rule one multiply per side.
        """
        n_points = xs.shape[0]
        out = np.empty((self.n_leds, 4 * n_points))
        gains = out[:, 2 * n_points : 3 * n_points]
        dx, dy, d2 = self._distances_squared(xs, ys)
        np.power(d2, self._minus_half_exponent, out=gains)
        gains *= self._factor
        gains *= d2 <= self._max_d2
        if self.has_tilt:
            factor, per_x, per_y, _ = self._tilt(dx, dy, np.sqrt(self._dz2))
            gains *= factor
        slope = self._minus_twice_half_exponent * gains
        slope /= d2
        np.multiply(slope, dx, out=out[:, :n_points])
        np.multiply(slope, dy, out=out[:, n_points : 2 * n_points])
        if self.has_tilt:
            out[:, :n_points] += gains * per_x
            out[:, n_points : 2 * n_points] += gains * per_y
        if self.has_beams:
            beam, along_x, along_y, _ = self._beam(dx, dy, np.sqrt(self._dz2), d2)
            out[:, :n_points] *= beam
            out[:, :n_points] += gains * along_x
            out[:, n_points : 2 * n_points] *= beam
            out[:, n_points : 2 * n_points] += gains * along_y
            gains *= beam
        if self.diffuse is not None:
            values, along_x, along_y, _ = self.diffuse.evaluate(xs, ys)
            gains += values * self._pilot_over_scale
            out[:, :n_points] += along_x * self._pilot_over_scale
            out[:, n_points : 2 * n_points] += along_y * self._pilot_over_scale
        out[:, 3 * n_points :] = gains
        return out

    def gains_xyz(self, xs: FloatArray, ys: FloatArray, zs: FloatArray) -> FloatArray:
        """``g`` at receivers at heights ``zs`` (all shapes (P,)), shape (M, P)."""
        return self.gradients_xyz(xs, ys, zs)[:, 3 * xs.shape[0] : 4 * xs.shape[0]].copy()

    def gradients_xyz(self, xs: FloatArray, ys: FloatArray, zs: FloatArray) -> FloatArray:
        """Columns ``[dg/dx | dg/dy | dg/dz | g | g | g]`` of shape (M, 6P) at ``(xs, ys, zs)``.

        With ``D = z_led - z``: ``h = pref D^(m+1) / d^(m+3)``, ``dh/dx = -(m+3) h dx / d^2``
        and ``dh/dz = -h ((m+1) / D - (m+3) D / d^2)``.
        """
        n_points = xs.shape[0]
        out = np.empty((self.n_leds, 6 * n_points))
        dx = xs - self._led_x
        dy = ys - self._led_y
        drop = self._led_z - zs
        drop = np.maximum(drop, 1e-9)
        d2 = dx * dx + dy * dy + drop * drop
        gains = out[:, 3 * n_points : 4 * n_points]
        np.power(d2, self._minus_half_exponent, out=gains)
        gains *= np.power(drop, self._orders_plus_one)
        gains *= self._free_height_factor
        gains *= drop * drop >= self.cos_fov2 * d2
        if self.has_tilt:
            factor, per_x, per_y, per_z = self._tilt(dx, dy, drop)
            gains *= factor
        slope = -self._orders_plus_three * gains / d2
        np.multiply(slope, dx, out=out[:, :n_points])
        np.multiply(slope, dy, out=out[:, n_points : 2 * n_points])
        np.multiply(
            gains,
            self._orders_plus_three * drop / d2 - self._orders_plus_one / drop,
            out=out[:, 2 * n_points : 3 * n_points],
        )
        if self.has_tilt:
            out[:, :n_points] += gains * per_x
            out[:, n_points : 2 * n_points] += gains * per_y
            out[:, 2 * n_points : 3 * n_points] += gains * per_z
        if self.has_beams:
            beam, along_x, along_y, along_z = self._beam(dx, dy, drop, d2)
            for block, along in enumerate((along_x, along_y, along_z)):
                part = out[:, block * n_points : (block + 1) * n_points]
                part *= beam
                part += gains * along
            gains *= beam
        if self.diffuse is not None:
            values, along_x, along_y, along_z = self.diffuse.evaluate(xs, ys, zs)
            gains += values * self._pilot_over_scale
            out[:, :n_points] += along_x * self._pilot_over_scale
            out[:, n_points : 2 * n_points] += along_y * self._pilot_over_scale
            out[:, 2 * n_points : 3 * n_points] += along_z * self._pilot_over_scale
        out[:, 4 * n_points : 5 * n_points] = gains
        out[:, 5 * n_points :] = gains
        return out

    def _tilt(
        self, dx: FloatArray, dy: FloatArray, drop: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The tilted LEDs' factor ``(c / D)^m`` (0 behind the face) and the log-derivatives
        it adds along x, y, z, each (M, P); ``drop`` is ``D``, (M, 1) or (M, P)."""
        facing = self._normal_x * dx + self._normal_y * dy - self._normal_z * drop
        ahead = facing > 0
        safe = np.where(ahead, facing, 1.0)
        factor = np.where(ahead, np.power(safe / drop, self._orders), 0.0)
        per_x = self._orders * self._normal_x / safe
        per_y = self._orders * self._normal_y / safe
        per_z = self._orders * (self._normal_z / safe + 1.0 / drop)
        return factor, per_x, per_y, per_z

    def beam_towards(self, to_receiver: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The beams' intensity (M, P) and its gradient (M, P, 3) w.r.t. the receiver at
        ``r - s = to_receiver`` (M, P, 3); rows of Lambertian LEDs 1 and 0."""
        beam, along_x, along_y, along_z = self._beam(
            to_receiver[:, :, 0],
            to_receiver[:, :, 1],
            -to_receiver[:, :, 2],
            np.einsum("mpk,mpk->mp", to_receiver, to_receiver),
        )
        return beam, np.stack((along_x, along_y, along_z), axis=-1)

    def _beam(
        self, dx: FloatArray, dy: FloatArray, drop: FloatArray, d2: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The beams' intensity ``I(c)`` and its derivatives along x, y, z, each (M, P);
        ``drop`` is ``D``, (M, 1) or (M, P). Rows of Lambertian LEDs are 1 and 0."""
        dist = np.sqrt(d2)
        cosines = (self._normal_x * dx + self._normal_y * dy - self._normal_z * drop) / dist
        beam, slope = evaluate_beams(self.beams, cosines)
        slope = slope / dist
        along_x = slope * (self._normal_x - cosines * dx / dist)
        along_y = slope * (self._normal_y - cosines * dy / dist)
        along_z = slope * (self._normal_z + cosines * drop / dist)
        return beam, along_x, along_y, along_z

    def _distances_squared(
        self, xs: FloatArray, ys: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        dx = xs - self._led_x
        dy = ys - self._led_y
        d2 = dx * dx
        d2 += dy * dy
        d2 += self._dz2
        return dx, dy, d2
