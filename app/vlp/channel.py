"""The line-of-sight Lambertian channel (paper eqs. 1-3).

For an LED pointing down and a detector pointing up, ``cos(alpha) = cos(phi) = dz / d``, so

.. math::

    h = \\frac{(m+1) A\\, G_f\\, G_c}{2 \\pi}\\, \\frac{dz^{m+1}}{d^{m+3}}, \\quad \\phi \\le FOV,

and 0 outside the field of view. Its gradient with respect to the receiver's horizontal
position ``p`` is ``-(m+3) h (p - s) / d^2`` (``s`` the LED's horizontal position), the
expression behind both the Cramér-Rao bound and the continuous solvers.

A tilted LED (layout ``normal`` ``n`` other than straight down) emits at
``cos(alpha) = n . (r - s) / d`` towards a receiver at ``r``: with ``c = n . (r - s)`` and
``D = z_led - z`` the gain is the straight-down one times ``(c / D)^m`` (0 where ``c <= 0``,
behind the LED's face), and its gradient gains ``m h n / c`` from that factor (``n_xy`` on
the receivers' plane; ``n + e_z c / D`` in 3-D, the ``e_z`` part cancelling the straight-down
factor's own). For ``n = (0, 0, -1)``, ``c = D`` and nothing changes.

An LED with a tabulated beam (layout ``beam``, :mod:`app.vlp.beams`) has order ``m = 0`` here,
so the expressions above give ``cos(phi) / d^2`` times its prefactor, and the gain is then
multiplied by the beam's intensity ``I(cos alpha)``, ``cos(alpha) = n . (r - s) / d``; the
gradient gains ``h I'(c) / I(c)`` times ``dc/dr = n / d - c (r - s) / d^2``.
"""

from __future__ import annotations

import math

import numpy as np

from .beams import beam_arrays, evaluate_beams
from .errors import GeometryError
from .layout import Layout
from .typing import FloatArray

__all__ = [
    "channel_gain_gradients",
    "channel_gains",
    "concentrator_gain",
    "lambertian_order",
    "led_beam_factors",
    "led_constants",
    "led_tilt_factors",
    "los_gain_gradients",
    "los_gains",
]


def lambertian_order(half_power_angle_deg: float | FloatArray) -> FloatArray:
    """Lambertian order ``m = -ln 2 / ln cos(half_power_angle)``.

    Parameters
    ----------
    half_power_angle_deg : float or ndarray of shape (M,)
        Half-power semi-angle, degrees, in (0, 90).

    Returns
    -------
    m : ndarray of shape () or (M,)

    Examples
    --------
    >>> round(float(lambertian_order(60.0)), 6)
    1.0
    """
    angle = np.asarray(half_power_angle_deg, dtype=np.float64)
    if np.any(~np.isfinite(angle)) or np.any(angle <= 0) or np.any(angle >= 90):
        raise GeometryError(f"half-power angle must be in (0, 90) degrees, got {angle!r}")
    return np.asarray(-math.log(2.0) / np.log(np.cos(np.deg2rad(angle))), dtype=np.float64)


def concentrator_gain(refractive_index: float, fov_deg: float) -> float:
    """Gain of an ideal non-imaging concentrator, ``n^2 / sin^2(FOV)`` (paper eq. 3).

    Examples
    --------
    >>> round(concentrator_gain(1.5, 60.0), 6)
    3.0
    """
    sine = math.sin(math.radians(fov_deg)) if 0 < fov_deg <= 90 else 0.0
    if sine == 0.0:  # also a positive fov_deg so small that its sine underflows
        raise GeometryError(f"fov_deg must be in (0, 90], got {fov_deg!r}", field="fov_deg")
    return float(refractive_index**2 / sine**2)


def led_constants(layout: Layout) -> tuple[FloatArray, FloatArray]:
    """Per-LED Lambertian order ``m`` and prefactor ``(m+1) A G_f G_c / (2 pi)``.

    An LED with a tabulated beam has ``m = 0`` and the prefactor
    ``A G_f G_c / (2 pi int_0^1 I dc)`` (its beam's intensity, on the axis 1, multiplies
    the gain: :func:`led_beam_factors`).

    Returns
    -------
    orders : ndarray of shape (M,)
    prefactors : ndarray of shape (M,), m^2 (the detector area's unit)
    """
    rx = layout.receiver
    orders = np.atleast_1d(lambertian_order(layout.half_power_angles_deg))
    gain = rx.area * rx.filter_gain * concentrator_gain(rx.refractive_index, rx.fov_deg)
    prefactors = (orders + 1.0) * gain / (2.0 * math.pi)
    for i, beam in enumerate(layout.beams):
        if beam is not None:
            orders[i] = 0.0
            prefactors[i] = gain / (2.0 * math.pi * beam.hemisphere_integral())
    return orders, prefactors


def led_beam_factors(layout: Layout, to_receiver: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Each LED's tabulated beam towards receivers, and its gradient.

    Parameters
    ----------
    layout : Layout
    to_receiver : ndarray of shape (M, P, 3)
        ``r - s``: receiver minus LED, metres.

    Returns
    -------
    factors : ndarray of shape (M, P)
        ``I(c)``, ``c = n . (r - s) / d``; exactly 1 for Lambertian LEDs.
    gradients : ndarray of shape (M, P, 3), per metre
        ``dI/dr = I'(c) (n / d - c (r - s) / d^2)``; 0 for Lambertian LEDs.
    """
    normals = layout.led_normals
    dist_sq = np.einsum("mpk,mpk->mp", to_receiver, to_receiver)
    dist = np.sqrt(dist_sq)
    cosines = np.einsum("mpk,mk->mp", to_receiver, normals) / dist
    factors, slopes = evaluate_beams(beam_arrays(layout.beams), cosines)
    along = normals[:, None, :] / dist[:, :, None] - (cosines / dist_sq)[:, :, None] * to_receiver
    return factors, slopes[:, :, None] * along


def channel_gains(layout: Layout, points: FloatArray) -> FloatArray:
    """DC gains ``h_ij`` of every LED at receiver points on the receivers' plane.

    Parameters
    ----------
    layout : Layout
    points : ndarray of shape (P, 2)
        Receiver positions ``(x, y)``, metres, at ``z = grid.receiver_height``.

    Returns
    -------
    gains : ndarray of shape (M, P)
        Dimensionless DC gains; exactly 0 outside the receiver's field of view.

    Examples
    --------
    >>> from app.vlp.layout import Grid, Layout, Led, Receiver, Room
    >>> lay = Layout(Room(4, 4, 3), Grid(1.0, 0.85), (Led(2, 2, 3, 70.0),),
    ...              Receiver(1e-4, 60.0, 1.0, 1.5))
    >>> float(channel_gains(lay, np.array([[2.0, 2.0]]))[0, 0])  # doctest: +ELLIPSIS
    1.70023...e-05
    """
    gains, (offsets, _, _) = _gains_and_offsets(layout, points)
    if layout.has_beams:
        gains = gains * led_beam_factors(layout, _to_receiver(layout, offsets))[0]
    return gains


def channel_gain_gradients(layout: Layout, points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Gains and their gradients with respect to the receiver's ``(x, y)``.

    Returns
    -------
    gains : ndarray of shape (M, P)
    gradients : ndarray of shape (M, P, 2), per metre
        ``d h_ij / d p_j = -(m_i + 3) h_ij (p_j - s_i) / d_ij^2``; 0 outside the FOV.
    """
    gains, (offsets, dist_sq, orders) = _gains_and_offsets(layout, points)
    scale = -(orders[:, None] + 3.0) * gains / dist_sq
    gradients = scale[:, :, None] * offsets
    if layout.has_tilted_leds:
        _, facing = led_tilt_factors(layout, _to_receiver(layout, offsets))
        normals = layout.led_normals
        safe = np.where(gains > 0, facing, 1.0)
        gradients += (orders[:, None] * gains / safe)[:, :, None] * normals[:, None, :2]
    if layout.has_beams:
        return _times_beam(layout, gains, gradients, _to_receiver(layout, offsets))
    return gains, gradients


def led_tilt_factors(layout: Layout, to_receiver: FloatArray) -> tuple[FloatArray, FloatArray]:
    """What each LED's tilt does to its straight-down gain towards receivers.

    Parameters
    ----------
    layout : Layout
    to_receiver : ndarray of shape (M, P, 3)
        ``r - s``: receiver minus LED, metres.

    Returns
    -------
    factors : ndarray of shape (M, P)
        ``(c / D)^m`` with ``c = n . (r - s)``, ``D = z_led - z``: exactly 1 for LEDs that
        point straight down, 0 where the receiver is behind the LED's face (``c <= 0``).
    facing : ndarray of shape (M, P)
        ``c`` (``D`` for LEDs pointing straight down).
    """
    normals = layout.led_normals
    drop = -to_receiver[:, :, 2]
    facing = np.einsum("mpk,mk->mp", to_receiver, normals)
    factors = np.ones(drop.shape)
    orders, _ = led_constants(layout)
    for i, led in enumerate(layout.leds):
        if not led.tilted or led.beam is not None:
            facing[i] = drop[i]
            continue
        ahead = (facing[i] > 0) & (drop[i] > 0)
        ratio = np.where(ahead, facing[i], 1.0) / np.where(ahead, drop[i], 1.0)
        factors[i] = np.where(ahead, ratio ** orders[i], 0.0)
    return factors, facing


def _gains_and_offsets(
    layout: Layout, points: FloatArray
) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray]]:
    """Gains on the plane without the beams' factor (:func:`_times_beam` adds it) and the
    offsets, squared distances and orders they came from."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    leds = layout.led_positions
    orders, prefactors = led_constants(layout)
    offsets = pts[None, :, :] - leds[:, None, :2]  # (M, P, 2): receiver minus LED
    dz = leds[:, 2] - layout.grid.receiver_height  # (M,)
    dist_sq = np.einsum("mpk,mpk->mp", offsets, offsets) + dz[:, None] ** 2
    cos_incidence = dz[:, None] / np.sqrt(dist_sq)
    in_view = cos_incidence >= math.cos(math.radians(layout.receiver.fov_deg)) - 1e-15
    gains = prefactors[:, None] * cos_incidence ** (orders[:, None] + 1.0) / dist_sq
    gains = np.where(in_view, gains, 0.0)
    if layout.has_tilted_leds:
        gains = gains * led_tilt_factors(layout, _to_receiver(layout, offsets))[0]
    return gains, (offsets, dist_sq, orders)


def _times_beam(
    layout: Layout, gains: FloatArray, gradients: FloatArray, to_receiver: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Gains ``h`` (M, P) and gradients (M, P, k) of the Lambertian part times the LEDs'
    beams: ``h I`` and ``grad(h) I + h grad(I)`` (the first k of x, y, z)."""
    beam, beam_gradients = led_beam_factors(layout, to_receiver)
    k = gradients.shape[2]
    return gains * beam, gradients * beam[:, :, None] + gains[:, :, None] * beam_gradients[..., :k]


def _to_receiver(layout: Layout, offsets: FloatArray) -> FloatArray:
    """``r - s`` (M, P, 3) for receivers on the plane at horizontal ``offsets`` (M, P, 2)."""
    dz = layout.led_positions[:, 2] - layout.grid.receiver_height
    return np.concatenate(
        (offsets, np.broadcast_to(-dz[:, None, None], (*offsets.shape[:2], 1))), axis=2
    )


def los_gains(
    layout: Layout, points_xyz: FloatArray, normals: FloatArray | None = None
) -> FloatArray:
    """Line-of-sight gains at receivers anywhere in the room, with any photodiode normal.

    Parameters
    ----------
    layout : Layout
    points_xyz : ndarray of shape (P, 3)
        Receiver positions ``(x, y, z)``, metres.
    normals : ndarray of shape (P, 3), default=None
        Unit normals of the photodiodes; None means straight up ``(0, 0, 1)``.

    Returns
    -------
    gains : ndarray of shape (M, P)
        ``h = (m+1)/(2 pi d^2) cos^m(alpha) A G_f G_c cos(phi)`` with ``cos(alpha) =
        n_led . (r - s) / d`` (``(z_led - z) / d`` for an LED pointing down) and
        ``cos(phi) = n . (s - r) / d``; 0 when ``phi > FOV``, ``cos(phi) <= 0``, the LED is
        not above the receiver or the receiver is behind the LED's face.

    Notes
    -----
    The generalised Lambertian LoS gain (Komine and Nakagawa 2004). For upward normals at
    ``grid.receiver_height`` it equals :func:`channel_gains`.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> lay = paper_layout()
    >>> flat = channel_gains(lay, np.array([[1.1, 2.3]]))
    >>> bool(np.allclose(los_gains(lay, np.array([[1.1, 2.3, 0.85]])), flat))
    True
    """
    gains, (to_led, _, _, _) = _los_parts(layout, points_xyz, normals)
    if layout.has_beams:
        gains = gains * led_beam_factors(layout, -to_led)[0]
    return gains


def los_gain_gradients(
    layout: Layout, points_xyz: FloatArray, normals: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """LoS gains and their analytic gradients with respect to the receiver's ``(x, y, z)``.

    Parameters
    ----------
    layout : Layout
    points_xyz : ndarray of shape (P, 3)
        Receiver positions, metres.
    normals : ndarray of shape (P, 3), default=None
        Unit photodiode normals (held fixed); None means straight up.

    Returns
    -------
    gains : ndarray of shape (M, P)
    gradients : ndarray of shape (M, P, 3), per metre
        With ``u = s - r`` (receiver to LED) and ``h = k u_z^m (n . u) |u|^-(m+3)``:
        ``dh/dr = -h (m e_z / u_z + n / (n . u) - (m + 3) u / |u|^2)``; 0 outside the FOV.
    """
    gains, (to_led, dist_sq, cos_phi_num, orders) = _los_parts(layout, points_xyz, normals)
    nrm = _normals(normals, to_led.shape[1])
    height = to_led[:, :, 2]
    visible = gains > 0
    safe_height = np.where(visible, height, 1.0)
    safe_num = np.where(visible, cos_phi_num, 1.0)
    bracket = (
        (orders[:, None, None] * np.array([0.0, 0.0, 1.0])) / safe_height[:, :, None]
        + nrm[None, :, :] / safe_num[:, :, None]
        - (orders[:, None, None] + 3.0) * to_led / dist_sq[:, :, None]
    )
    if layout.has_tilted_leds:
        # d ln (c / D)^m / dr = m (n_led / c + e_z / D); 0 for LEDs pointing straight down.
        _, facing = led_tilt_factors(layout, -to_led)
        safe_facing = np.where(visible, facing, 1.0)
        normals = layout.led_normals
        tilt = orders[:, None, None] * (
            normals[:, None, :] / safe_facing[:, :, None]
            + np.array([0.0, 0.0, 1.0]) / safe_height[:, :, None]
        )
        bracket = bracket - tilt
    gradients = np.asarray(-gains[:, :, None] * bracket)
    if layout.has_beams:
        return _times_beam(layout, gains, gradients, -to_led)
    return gains, gradients


def _normals(normals: FloatArray | None, count: int) -> FloatArray:
    if normals is None:
        return np.tile(np.array([0.0, 0.0, 1.0]), (count, 1))
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if nrm.shape[0] != count:
        raise GeometryError(
            f"expected {count} normals (one per point), got shape {nrm.shape}", field="normals"
        )
    lengths = np.linalg.norm(nrm, axis=1)
    if not np.all(np.isfinite(lengths)) or np.any(np.abs(lengths - 1.0) > 1e-6):
        raise GeometryError("normals must be finite unit vectors", field="normals")
    return nrm


def _los_parts(
    layout: Layout, points_xyz: FloatArray, normals: FloatArray | None
) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray, FloatArray]]:
    """Gains anywhere without the beams' factor (:func:`_times_beam` adds it), and the
    vectors to the LEDs, squared distances, ``n . u`` and orders they came from."""
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    nrm = _normals(normals, pts.shape[0])
    orders, prefactors = led_constants(layout)
    to_led = layout.led_positions[:, None, :] - pts[None, :, :]  # (M, P, 3): u = s - r
    dist_sq = np.einsum("mpk,mpk->mp", to_led, to_led)
    dist = np.sqrt(dist_sq)
    cos_alpha = to_led[:, :, 2] / dist
    cos_phi_num = np.einsum("mpk,pk->mp", to_led, nrm)
    cos_phi = cos_phi_num / dist
    cos_fov = math.cos(math.radians(layout.receiver.fov_deg))
    visible = (cos_alpha > 0) & (cos_phi > 0) & (cos_phi >= cos_fov - 1e-15)
    safe_alpha = np.where(visible, cos_alpha, 1.0)
    gains = prefactors[:, None] * safe_alpha ** orders[:, None] * cos_phi / dist_sq
    if layout.has_tilted_leds:
        gains = gains * led_tilt_factors(layout, -to_led)[0]
    return np.where(visible, gains, 0.0), (to_led, dist_sq, cos_phi_num, orders)
