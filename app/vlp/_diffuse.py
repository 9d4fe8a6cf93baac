"""First-bounce diffuse gains (the model and its quadrature: see :mod:`app.vlp.reflections`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._diffuse_quadrature import (
    ON_PLANE_M,
    LedFrame,
    element_size,
    graded_rule,
    points_and_normals,
    receiver_kernel,
    room_surfaces,
)
from .channel import concentrator_gain, led_constants
from .errors import GeometryError
from .layout import Layout, Reflectance
from .typing import FloatArray

__all__ = ["diffuse_gains", "surface_flux_fractions", "view_factors"]


def diffuse_gains(
    layout: Layout,
    points_xyz: FloatArray,
    normals: FloatArray | None = None,
    *,
    reflectance: Reflectance | None = None,
    element_size_m: float | None = None,
) -> FloatArray:
    """First-bounce diffuse reflection gain of every LED at receiver points.

    Parameters
    ----------
    layout : Layout
    points_xyz : ndarray of shape (P, 3)
        Receiver positions, metres, inside the room.
    normals : ndarray of shape (P, 3), default=None
        Unit photodiode normals; None means straight up.
    reflectance : Reflectance, default=None
        Overrides ``layout.room.reflectance``; all gains are 0 when both are None.
    element_size_m : float, default=None
        Largest quadrature cell, metres (:data:`DEFAULT_ELEMENT_SIZE_M` when None); cells
        near the receiver and the LEDs are refined further (:data:`GRADING`).

    Returns
    -------
    gains : ndarray of shape (M, P)
        Dimensionless DC gains of the reflected light (same receiver optics as
        :func:`~app.vlp.channel.los_gains`: area, filter, concentrator, FOV).

    Raises
    ------
    GeometryError
        When a point lies outside the room, a normal is not a unit vector, or
        ``element_size_m`` is not positive.

    Notes
    -----
    A receiver exactly on a surface's plane gets nothing from that surface (it sees it edge
    on); the limit from inside the room is larger (about half the configuration factor of the
    wall's near part). :class:`~app.vlp.reflections.ReflectionTable` evaluates wall lines
    0.1 mm inside for that reason.

    Examples
    --------
    >>> from app.vlp.layout import Reflectance
    >>> from app.vlp.presets import paper_layout
    >>> lay = paper_layout()
    >>> gains = diffuse_gains(lay, np.array([[2.0, 2.0, 0.85]]), reflectance=Reflectance(0.7, 0, 0))
    >>> gains.shape, bool(np.all(gains > 0))
    ((16, 1), True)
    """
    pts, nrm = points_and_normals(layout, points_xyz, normals)
    size = element_size(element_size_m)
    rho = reflectance if reflectance is not None else layout.room.reflectance
    gains = np.zeros((layout.n_leds, pts.shape[0]))
    if rho is None:
        return gains
    rx = layout.receiver
    receiver_gain = rx.area * rx.filter_gain * concentrator_gain(rx.refractive_index, rx.fov_deg)
    cos_fov = math.cos(math.radians(rx.fov_deg))
    fov_rad = math.radians(rx.fov_deg)
    orders, _ = led_constants(layout)
    for surface in room_surfaces(layout, rho):
        if surface.reflectance == 0:
            continue
        frame = LedFrame.of(layout, surface, orders, size)
        if frame.active.size == 0:
            continue  # no LED lights this surface (e.g. the ceiling, LEDs flush with it)
        for p in range(pts.shape[0]):
            point, normal = pts[p], nrm[p]
            # The acceptance cone lies wholly on the surface's back side (e.g. the floor for
            # an upward receiver with FOV < 90 degrees): nothing to integrate.
            if math.acos(float(np.clip(normal @ surface.normal, -1.0, 1.0))) + fov_rad <= (
                math.pi / 2
            ):
                continue
            distance = float(surface.normal @ (point - surface.origin))
            if distance <= ON_PLANE_M:
                continue
            foot = point - surface.origin
            nodes_u, weights_u = graded_rule(
                surface.extent_u, [*frame.feet_u, (float(surface.axis_u @ foot), distance)], size
            )
            nodes_v, weights_v = graded_rule(
                surface.extent_v, [*frame.feet_v, (float(surface.axis_v @ foot), distance)], size
            )
            kernel = receiver_kernel(
                surface, nodes_u, nodes_v, point, normal, cos_fov, weights_u, weights_v
            )
            weighted = kernel * np.outer(weights_u, weights_v)  # (n_u, n_v)
            gains[:, p] += frame.contract(nodes_u, nodes_v, weighted)
    return np.asarray(gains * receiver_gain)


def surface_flux_fractions(
    layout: Layout, led_index: int, *, element_size_m: float | None = None
) -> dict[str, float]:
    """Fraction of one LED's emitted flux landing on each of the six surfaces.

    For a point Lambertian source of order ``m`` pointing down, the flux per unit area at
    ``q`` is ``(m+1)/(2 pi d^2) cos^m(alpha) cos(beta)``; the six fractions of a closed box
    add up to 1 (the energy check of the reflection model).

    Returns
    -------
    fractions : dict of str to float
        Keyed by :data:`SURFACES`.

    Raises
    ------
    GeometryError
        When ``led_index`` is out of range.
    """
    if not 0 <= led_index < layout.n_leds:
        raise GeometryError(
            f"led_index must be in [0, {layout.n_leds}), got {led_index}", field="led_index"
        )
    size = element_size(element_size_m)
    orders, _ = led_constants(layout)
    fractions: dict[str, float] = {}
    for surface in room_surfaces(layout):
        frame = LedFrame.of(layout, surface, orders, size, only_led=led_index)
        nodes_u, weights_u = graded_rule(surface.extent_u, frame.feet_u, size)
        nodes_v, weights_v = graded_rule(surface.extent_v, frame.feet_v, size)
        flux = frame.contract(nodes_u, nodes_v, np.outer(weights_u, weights_v))
        fractions[surface.name] = float(flux[0])
    return fractions


def view_factors(
    layout: Layout,
    point_xyz: FloatArray,
    normal: FloatArray | None = None,
    *,
    element_size_m: float | None = None,
) -> dict[str, float]:
    """Configuration factor from a receiver element to each surface, within its FOV.

    ``F = integral cos(beta2) cos(phi2) / (pi d^2) dA`` over the part of each surface inside
    the receiver's field of view: the receiver-side half of :func:`diffuse_gains` with a
    uniformly bright surface. With a 90-degree FOV the six factors add up to 1.

    Parameters
    ----------
    layout : Layout
    point_xyz : ndarray of shape (3,)
        Receiver position, metres, strictly inside the room.
    normal : ndarray of shape (3,), default=None
        Unit normal of the receiver; None means straight up.

    Returns
    -------
    factors : dict of str to float
        Keyed by :data:`SURFACES`.
    """
    pts, nrm = points_and_normals(
        layout,
        np.reshape(point_xyz, (1, 3)),
        None if normal is None else np.reshape(normal, (1, 3)),
    )
    size = element_size(element_size_m)
    cos_fov = math.cos(math.radians(layout.receiver.fov_deg))
    factors: dict[str, float] = {}
    for surface in room_surfaces(layout, Reflectance(0.0, 0.0, 0.0)):
        white = dataclasses.replace(surface, reflectance=1.0)
        foot = pts[0] - surface.origin
        distance = float(surface.normal @ foot)
        if distance <= ON_PLANE_M:
            factors[surface.name] = 0.0
            continue
        nodes_u, weights_u = graded_rule(
            surface.extent_u, [(float(surface.axis_u @ foot), distance)], size
        )
        nodes_v, weights_v = graded_rule(
            surface.extent_v, [(float(surface.axis_v @ foot), distance)], size
        )
        kernel = receiver_kernel(
            white, nodes_u, nodes_v, pts[0], nrm[0], cos_fov, weights_u, weights_v
        )
        factors[surface.name] = float(weights_u @ kernel @ weights_v)
    return factors
