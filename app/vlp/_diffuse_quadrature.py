"""Quadrature behind the diffuse-reflection gains: surfaces, graded Gauss rules, kernels.

Private: the public functions live in :mod:`app.vlp.reflections`, which documents the model.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .beams import Beam, beam_arrays, evaluate_beams
from .errors import GeometryError
from .layout import Layout, Reflectance
from .typing import BoolArray, FloatArray, IntArray

# Largest quadrature cell (metres). Each cell carries a 3 x 3 Gauss rule, so the far field of
# a smooth integrand is resolved far below this; near-field accuracy comes from GRADING.
DEFAULT_ELEMENT_SIZE_M = 0.25
# A cell is at most this fraction of its distance to the nearest foot point (receiver or LED).
GRADING = 0.25
# Gauss-Legendre points per cell and axis.
_GAUSS_POINTS = 3
# An LED or receiver closer than this to a plane is treated as lying on it (no grading there).
ON_PLANE_M = 1e-9
# LEDs closer to a plane than this many element sizes get cells graded towards their foot
# (farther ones light it smoothly enough for the uniform cells;
# docs/explanation/reflections.md#quadrature-the-element-size-and-why).
_LED_GRADING_REACH = 2.0
SURFACES = ("floor", "ceiling", "wall_x0", "wall_x1", "wall_y0", "wall_y1")


@dataclass(frozen=True)
class Surface:
    """One rectangle of the room: corner, in-plane unit axes and extents, inward normal."""

    name: str
    origin: FloatArray
    axis_u: FloatArray
    axis_v: FloatArray
    extent_u: float
    extent_v: float
    normal: FloatArray
    reflectance: float


def room_surfaces(layout: Layout, reflectance: Reflectance | None = None) -> tuple[Surface, ...]:
    """The six inner surfaces of the room box, each with its reflectance (0 when None).

    Returns
    -------
    surfaces : tuple of Surface
        In :data:`SURFACES` order: floor, ceiling, walls at x = 0, x = length, y = 0,
        y = width.
    """
    length, width, height = layout.room.length, layout.room.width, layout.room.height
    rho = reflectance or Reflectance(0.0, 0.0, 0.0)
    e_x, e_y, e_z = np.eye(3)
    origin = np.zeros(3)
    return (
        Surface("floor", origin, e_x, e_y, length, width, e_z, rho.floor),
        Surface("ceiling", height * e_z, e_x, e_y, length, width, -e_z, rho.ceiling),
        Surface("wall_x0", origin, e_y, e_z, width, height, e_x, rho.walls),
        Surface("wall_x1", length * e_x, e_y, e_z, width, height, -e_x, rho.walls),
        Surface("wall_y0", origin, e_x, e_z, length, height, e_y, rho.walls),
        Surface("wall_y1", width * e_y, e_x, e_z, length, height, -e_y, rho.walls),
    )


def element_size(element_size_m: float | None) -> float:
    size = DEFAULT_ELEMENT_SIZE_M if element_size_m is None else float(element_size_m)
    if not (math.isfinite(size) and size > 0):
        raise GeometryError(
            f"element_size_m must be a positive number, got {element_size_m!r}",
            field="element_size_m",
        )
    return size


def points_and_normals(
    layout: Layout, points_xyz: FloatArray, normals: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    room = layout.room
    upper = np.array([room.length, room.width, room.height])
    if not np.all(np.isfinite(pts)) or np.any(pts < 0) or np.any(pts > upper):
        raise GeometryError("receiver points must lie inside the room", field="points")
    if normals is None:
        return pts, np.tile(np.array([0.0, 0.0, 1.0]), (pts.shape[0], 1))
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    lengths = np.linalg.norm(nrm, axis=1)
    if nrm.shape[0] != pts.shape[0] or not np.all(np.abs(lengths - 1.0) <= 1e-6):
        raise GeometryError("normals must be one unit vector per point", field="normals")
    return pts, nrm


@dataclass(frozen=True)
class LedFrame:
    """The LEDs in one surface's frame: in-plane coordinates, height above the plane, order.

    ``contract`` integrates the LEDs' irradiance against weights on a tensor mesh without
    forming the (M, n, 3) offsets: ``d^2 = (u_i - u)^2 + ((v_i - v)^2 + b_i^2)`` is a sum of an
    (M, n_u) and an (M, n_v) part. Only the ``active`` LEDs, in front of the plane and above
    some of it, are kept (the others light none of it).
    """

    n_leds: int
    active: IntArray
    led_u: FloatArray
    led_v: FloatArray
    led_height: FloatArray  # b_i: distance in front of the plane (cos(beta1) = b / d)
    led_z: FloatArray
    orders: FloatArray
    v_is_z: bool  # walls: v runs along z from the floor; floor/ceiling: z is constant
    plane_z: float
    # The LEDs' normals along (axis_u, axis_v, normal) of the surface, (M, 3), and which of
    # them are tilted (their irradiance is then computed on the whole mesh, not factored).
    led_normals: FloatArray
    tilted: BoolArray
    feet_u: tuple[tuple[float, float], ...]
    feet_v: tuple[tuple[float, float], ...]
    beams: tuple[Beam | None, ...] = ()

    @classmethod
    def of(
        cls,
        layout: Layout,
        surface: Surface,
        orders: FloatArray,
        size: float,
        *,
        only_led: int | None = None,
    ) -> LedFrame:
        leds = layout.led_positions
        normals = layout.led_normals
        # LEDs with a tabulated beam take the whole-mesh path too (order 0 there, times
        # their beam's intensity: _tilted_flux).
        tilted = np.array([led.tilted or led.beam is not None for led in layout.leds], dtype=bool)
        beams = layout.beams
        if only_led is not None:
            beams = beams[only_led : only_led + 1]
            leds, orders = leds[only_led : only_led + 1], orders[only_led : only_led + 1]
            normals, tilted = normals[only_led : only_led + 1], tilted[only_led : only_led + 1]
        offsets = leds - surface.origin
        lowest_z = float(surface.origin[2]) if surface.axis_v[2] == 0 else 0.0
        active = np.flatnonzero(
            (offsets @ surface.normal > ON_PLANE_M) & (leds[:, 2] > lowest_z + ON_PLANE_M)
        )
        n_leds = leds.shape[0]
        leds, orders, offsets = leds[active], orders[active], offsets[active]
        normals, tilted = normals[active], tilted[active]
        beams = tuple(beams[i] for i in active)
        frame = np.array([surface.axis_u, surface.axis_v, surface.normal])
        led_u, led_v = offsets @ surface.axis_u, offsets @ surface.axis_v
        led_height = offsets @ surface.normal
        # Grade towards an LED's foot only where it is close enough to need finer cells.
        near = led_height < size * _LED_GRADING_REACH
        return cls(
            n_leds=n_leds,
            active=active,
            led_u=led_u,
            led_v=led_v,
            led_height=led_height,
            led_z=leds[:, 2],
            orders=orders,
            v_is_z=bool(abs(surface.axis_v[2]) == 1.0),
            plane_z=float(surface.origin[2]),
            feet_u=tuple(zip(led_u[near].tolist(), led_height[near].tolist(), strict=True)),
            feet_v=tuple(zip(led_v[near].tolist(), led_height[near].tolist(), strict=True)),
            led_normals=normals @ frame.T,
            tilted=tilted,
            beams=beams,
        )

    def contract(self, nodes_u: FloatArray, nodes_v: FloatArray, weights: FloatArray) -> FloatArray:
        """``sum_(u,v) E_i(u, v) w(u, v)`` for every LED, shape (M,)."""
        flux = np.zeros(self.n_leds)
        if self.active.size:
            flux[self.active] = self._contract_active(nodes_u, nodes_v, weights)
        return flux

    def _contract_active(
        self, nodes_u: FloatArray, nodes_v: FloatArray, weights: FloatArray
    ) -> FloatArray:
        across = (self.led_u[:, None] - nodes_u[None, :]) ** 2  # (M, n_u)
        along = (self.led_v[:, None] - nodes_v[None, :]) ** 2 + self.led_height[:, None] ** 2
        if self.v_is_z:
            drop = self.led_z[:, None] - nodes_v[None, :]  # (M, n_v): LED above the node
        else:
            drop = np.broadcast_to((self.led_z - self.plane_z)[:, None], along.shape)
        lit_v = drop > 0
        orders = self.orders[:, None]
        # E = (m+1)/(2 pi) b dz^m / d^(m+3), split into its v-only factor and the d-power.
        v_factor = np.where(
            lit_v,
            (orders + 1.0)
            / (2.0 * math.pi)
            * self.led_height[:, None]
            * np.where(lit_v, drop, 1.0) ** orders,
            0.0,
        )
        inner = np.empty_like(v_factor)  # (M, n_v)
        for order in np.unique(self.orders):
            group = self.orders == order
            dist_sq = across[group][:, :, None] + along[group][:, None, :]  # (G, n_u, n_v)
            falloff = _inverse_power(dist_sq, (float(order) + 3.0) / 2.0)
            inner[group] = np.einsum("guv,uv->gv", falloff, weights)
        flux = np.einsum("mv,mv->m", inner, v_factor)
        for i in np.flatnonzero(self.tilted):
            flux[i] = self._tilted_flux(int(i), nodes_u, nodes_v, weights, across[i], along[i])
        return np.asarray(flux)

    def _tilted_flux(
        self,
        i: int,
        nodes_u: FloatArray,
        nodes_v: FloatArray,
        weights: FloatArray,
        across: FloatArray,
        along: FloatArray,
    ) -> float:
        """``sum E w`` of a tilted LED: ``E = (m+1)/(2 pi) b c^m / d^(m+3)`` with
        ``c = n . (node - s)`` (0 where ``c <= 0``, behind its face), on the whole mesh; for
        an LED with a tabulated beam (order 0) times ``I(c / d) / int_0^1 I``."""
        n_u, n_v, n_n = self.led_normals[i]
        facing = (
            n_u * (nodes_u[:, None] - self.led_u[i])
            + n_v * (nodes_v[None, :] - self.led_v[i])
            - n_n * self.led_height[i]
        )
        order = float(self.orders[i])
        dist_sq = across[:, None] + along[None, :]
        cosines = facing / np.sqrt(dist_sq)  # before _inverse_power overwrites dist_sq
        lit = facing > 0
        irradiance = np.where(
            lit,
            (order + 1.0)
            / (2.0 * math.pi)
            * self.led_height[i]
            * np.where(lit, facing, 1.0) ** order
            * _inverse_power(dist_sq, (order + 3.0) / 2.0),
            0.0,
        )
        beam = self.beams[i] if self.beams else None
        if beam is not None:
            intensity, _ = evaluate_beams(beam_arrays([beam]), cosines.reshape(1, -1))
            irradiance = irradiance * intensity.reshape(cosines.shape) / beam.hemisphere_integral()
        return float(np.sum(irradiance * weights))


def graded_rule(
    extent: float, feet: list[tuple[float, float]] | tuple[tuple[float, float], ...], size: float
) -> tuple[FloatArray, FloatArray]:
    """1-D composite Gauss rule on [0, extent]: cells <= size and <= GRADING x the distance
    to every foot point ``(centre, height)`` (the union of each foot's graded edges)."""
    edge_sets = [np.linspace(0.0, extent, max(1, math.ceil(extent / size - 1e-9)) + 1)]
    for centre, height in feet:
        offsets = _graded_offsets(height, size)
        edge_sets.append(centre + offsets)
        edge_sets.append(centre - offsets)
    edges = np.unique(np.clip(np.concatenate(edge_sets), 0.0, extent))
    edges = edges[np.concatenate(([True], np.diff(edges) > 1e-12 * max(extent, 1.0)))]
    lows, widths = edges[:-1], np.diff(edges)
    base_nodes, base_weights = _gauss_rule()
    nodes = lows[:, None] + 0.5 * widths[:, None] * (base_nodes[None, :] + 1.0)
    weights = 0.5 * widths[:, None] * base_weights[None, :]
    return nodes.ravel(), weights.ravel()


@functools.lru_cache(maxsize=4096)
def _graded_offsets(height: float, size: float) -> FloatArray:
    """Offsets 0 = s_0 < s_1 < ... from a foot at ``height`` off the plane, with
    ``s_(k+1) - s_k = min(size, GRADING * hypot(s_k, height))``, out to ``size / GRADING``
    (beyond which the uniform cells already satisfy the bound)."""
    offsets = [0.0]
    reach = size / GRADING
    while offsets[-1] < reach:
        offsets.append(offsets[-1] + min(size, GRADING * math.hypot(offsets[-1], height)))
    return np.array(offsets)


def _inverse_power(values: FloatArray, power: float) -> FloatArray:
    """``values ** -power`` (overwrites ``values``), by multiplication when ``2 power`` is a
    whole number (m = 1, 2, ..., the common LEDs): several times faster than ``pow``."""
    twice = 2.0 * power
    if twice != round(twice) or not 0 < twice <= 16:
        return np.asarray(np.exp(-power * np.log(values)))
    inverse = np.divide(1.0, values, out=values)
    whole, half = divmod(round(twice), 2)
    result = np.sqrt(inverse) if whole == 0 else inverse.copy() if whole == 1 else inverse**2
    for _ in range(whole - 2):
        result *= inverse
    if half and whole > 0:
        result *= np.sqrt(inverse)
    return result


@functools.lru_cache(maxsize=1)
def _gauss_rule() -> tuple[FloatArray, FloatArray]:
    nodes, weights = np.polynomial.legendre.leggauss(_GAUSS_POINTS)
    return np.asarray(nodes), np.asarray(weights)


def receiver_kernel(
    surface: Surface,
    nodes_u: FloatArray,
    nodes_v: FloatArray,
    point: FloatArray,
    normal: FloatArray,
    cos_fov: float,
    weights_u: FloatArray,
    weights_v: FloatArray,
) -> FloatArray:
    """``rho cos(beta2) cos(phi2) / (pi d2^2)`` inside the FOV on the mesh, (n_u, n_v), 1/m^2.

    The FOV edge cuts cells, where a hard 0/1 mask would make the rule only first order in
    the cell size. Each node is weighted instead by the fraction of its own patch (its Gauss
    weights along u and v) inside the cone, from the linearised ``cos(phi2) - cos(FOV)``.
    """
    foot = point - surface.origin
    along_u = nodes_u - surface.axis_u @ foot  # in-plane offsets from the foot point
    along_v = nodes_v - surface.axis_v @ foot
    height = float(surface.normal @ foot)
    dist_sq = along_u[:, None] ** 2 + along_v[None, :] ** 2 + height**2
    dist = np.sqrt(dist_sq)
    # receiver -> node = along_u e_u + along_v e_v - height n
    normal_u, normal_v = float(normal @ surface.axis_u), float(normal @ surface.axis_v)
    facing = (
        along_u[:, None] * normal_u
        + along_v[None, :] * normal_v
        - height * float(normal @ surface.normal)
    )
    cos_beta = height / dist
    cos_phi = facing / dist
    # d cos(phi) / du = n_u / d - cos(phi) along_u / d^2 (and likewise along v)
    slope_u = (normal_u - cos_phi * along_u[:, None] / dist) / dist
    slope_v = (normal_v - cos_phi * along_v[None, :] / dist) / dist
    spread = np.abs(slope_u) * weights_u[:, None] + np.abs(slope_v) * weights_v[None, :]
    value = surface.reflectance * cos_beta * cos_phi / (math.pi * dist_sq)
    if cos_fov <= 0:  # a 90-degree FOV: the integrand falls continuously to 0 at the edge
        return np.where(cos_phi > 0, value, 0.0)
    inside = np.clip(0.5 + (cos_phi - cos_fov) / np.maximum(spread, 1e-300), 0.0, 1.0)
    return np.where(cos_phi > 0, value * inside, 0.0)
