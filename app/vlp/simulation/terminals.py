"""Per-terminal pilot amplitudes in a room that is not the layout's ideal model.

The true channel is computed independently of any fingerprint: exact line of sight from the
perturbed LEDs to raised, tilted photodiodes (:func:`~app.vlp.channel.los_gains`) plus the
exact first diffuse bounce off the true surfaces (:func:`~app.vlp.reflections.diffuse_gains`
with :data:`TRUE_ELEMENT_SIZE_M`, finer cells than the fingerprints'), times each terminal's
gain and the common scale, plus i.i.d. Gaussian noise. The noise level follows
:func:`~app.vlp.simulation.noise_std_for_snr` on the NOMINAL line-of-sight fingerprint of the
layout, so a given SNR means the same noise in every condition.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..channel import channel_gains, los_gains
from ..errors import GeometryError
from ..fingerprints import Fingerprint, build_fingerprint
from ..layout import Layout, Led
from ..reflections import diffuse_gains
from ..rng import RandomState, as_generator
from ..typing import FloatArray
from ._ideal import noise_std_for_snr
from .impairments import Impairments

__all__ = ["TRUE_ELEMENT_SIZE_M", "SimulatedTerminals", "simulate_terminals"]

# Largest quadrature cell of the true diffuse bounce (the fingerprints use the default, 0.25).
TRUE_ELEMENT_SIZE_M = 0.1
# Terminals stay this far below the lowest LED and above the floor.
_HEIGHT_MARGIN_M = 0.05
# Perturbed half-power angles stay within this range, degrees.
_HALF_POWER_RANGE_DEG = (5.0, 85.0)


@dataclass(frozen=True)
class SimulatedTerminals:
    """K simulated terminals and what they measured.

    Attributes
    ----------
    positions : ndarray of shape (K, 2)
        True ``(x, y)``, metres.
    heights : ndarray of shape (K,)
        True photodiode heights, metres.
    normals : ndarray of shape (K, 3)
        True photodiode unit normals.
    gains : ndarray of shape (K,)
        True terminal gains (1 = as modelled), without the common scale.
    true_layout : Layout
        The room as it really is: perturbed LEDs (positions, beams, pilots) and the true
        reflectance.
    amplitudes : ndarray of shape (K, M)
        Noisy per-terminal pilot amplitudes ``a_ik``.
    noise_std : float
        Standard deviation of the noise on each amplitude.
    """

    positions: FloatArray
    heights: FloatArray
    normals: FloatArray
    gains: FloatArray
    true_layout: Layout
    amplitudes: FloatArray
    noise_std: float


def simulate_terminals(
    layout: Layout,
    positions: FloatArray,
    impairments: Impairments,
    *,
    snr_db: float,
    rng: RandomState = None,
) -> SimulatedTerminals:
    """Draw the impairments and the noisy pilot amplitudes of K terminals.

    Parameters
    ----------
    layout : Layout
        The room as the service knows it.
    positions : ndarray of shape (K, 2)
        True ``(x, y)`` of the terminals, metres.
    impairments : Impairments
    snr_db : float
        SNR in our convention on the nominal line-of-sight fingerprint (``inf``: no noise).
    rng : Generator, int or None

    Returns
    -------
    SimulatedTerminals

    Notes
    -----
    Draw order (so a seed gives the same draws whatever else changes): LED amplitudes, LED
    half-power angles, LED positions, terminal gains, heights, tilts, then the noise; an
    impairment that is zero draws nothing. With :meth:`Impairments.ideal` the result equals
    :func:`~app.vlp.simulation.noisy_amplitudes` for the same generator.
    """
    gen = as_generator(rng)
    pts = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    n_terminals = pts.shape[0]
    true_layout = _true_layout(layout, impairments, gen)
    gains = _lognormal(gen, impairments.gain_sd, n_terminals)
    heights = _heights(layout, impairments.height_sd_m, n_terminals, gen)
    normals = _normals(impairments.tilt_max_deg, n_terminals, gen)
    xyz = np.column_stack((pts, heights))
    if impairments.height_sd_m == 0 and impairments.tilt_max_deg == 0:
        channel = channel_gains(true_layout, pts)  # the paper's flat, upward receivers
    else:
        channel = los_gains(true_layout, xyz, normals)
    if impairments.reflectance is not None:
        channel = channel + diffuse_gains(
            true_layout, xyz, normals, element_size_m=TRUE_ELEMENT_SIZE_M
        )
    clean = (channel * true_layout.pilot_amplitudes[:, None]).T  # (K, M)
    clean = clean * (gains * impairments.common_scale)[:, None]
    noise_std = _nominal_noise_std(layout, snr_db)
    amplitudes = clean + noise_std * gen.standard_normal(clean.shape)
    return SimulatedTerminals(
        positions=pts,
        heights=heights,
        normals=normals,
        gains=gains,
        true_layout=true_layout,
        amplitudes=np.asarray(amplitudes),
        noise_std=noise_std,
    )


def _nominal_noise_std(layout: Layout, snr_db: float) -> float:
    if math.isinf(snr_db) and snr_db > 0:
        return 0.0
    return noise_std_for_snr(_nominal_fingerprint(_line_of_sight(layout)), snr_db)


def _line_of_sight(layout: Layout) -> Layout:
    if layout.room.reflectance is None:
        return layout
    return dataclasses.replace(layout, room=dataclasses.replace(layout.room, reflectance=None))


@functools.lru_cache(maxsize=4)
def _nominal_fingerprint(layout: Layout) -> Fingerprint:
    return build_fingerprint(layout)


def _lognormal(gen: np.random.Generator, relative_sd: float, count: int) -> FloatArray:
    """Mean-1 log-normal factors with relative sd ``relative_sd`` (ones when 0, no draw)."""
    if relative_sd == 0:
        return np.ones(count)
    sigma = math.sqrt(math.log1p(relative_sd**2))
    return np.asarray(np.exp(sigma * gen.standard_normal(count) - 0.5 * sigma**2))


def _true_layout(layout: Layout, impairments: Impairments, gen: np.random.Generator) -> Layout:
    count = layout.n_leds
    amplitude = _lognormal(gen, impairments.led_amplitude_sd, count)
    angles = layout.half_power_angles_deg
    if impairments.led_half_power_sd_deg > 0:
        angles = np.clip(
            angles + impairments.led_half_power_sd_deg * gen.standard_normal(count),
            *_HALF_POWER_RANGE_DEG,
        )
    where = layout.led_positions[:, :2]
    if impairments.led_position_sd_m > 0:
        upper = np.array([layout.room.length, layout.room.width])
        where = np.clip(
            where + impairments.led_position_sd_m * gen.standard_normal((count, 2)), 0, upper
        )
    normals = layout.led_normals
    if impairments.led_tilt_max_deg > 0:
        # Drawn after every other LED tolerance: rooms without it draw as before it existed.
        normals = _tilted_normals(normals, impairments.led_tilt_max_deg, gen)
    leds = tuple(
        Led(
            x=float(where[i, 0]),
            y=float(where[i, 1]),
            z=led.z,
            half_power_angle_deg=float(angles[i]),
            pilot_amplitude=led.pilot_amplitude * float(amplitude[i]),
            normal=led.normal
            if impairments.led_tilt_max_deg == 0
            else (float(normals[i, 0]), float(normals[i, 1]), float(normals[i, 2])),
        )
        for i, led in enumerate(layout.leds)
    )
    room = dataclasses.replace(layout.room, reflectance=impairments.reflectance)
    return dataclasses.replace(layout, room=room, leds=leds)


def _tilted_normals(
    normals: FloatArray, largest_deg: float, gen: np.random.Generator
) -> FloatArray:
    """Each normal turned by a polar angle uniform in [0, largest_deg] towards a uniform
    azimuth (around two unit vectors across it)."""
    count = normals.shape[0]
    polar = math.radians(largest_deg) * np.asarray(gen.uniform(0.0, 1.0, (count,)))
    azimuth = np.asarray(gen.uniform(0.0, 2.0 * math.pi, (count,)))
    out = np.empty_like(normals)
    for i, n in enumerate(normals):
        across = np.array([1.0, 0.0, 0.0]) - n[0] * n
        across /= np.linalg.norm(across)
        other = np.cross(across, n)
        side = math.cos(float(azimuth[i])) * across + math.sin(float(azimuth[i])) * other
        out[i] = math.cos(float(polar[i])) * n + math.sin(float(polar[i])) * side
    return out


def _heights(layout: Layout, sd_m: float, count: int, gen: np.random.Generator) -> FloatArray:
    nominal = layout.grid.receiver_height
    if sd_m == 0:
        return np.full(count, nominal)
    highest = min(led.z for led in layout.leds) - _HEIGHT_MARGIN_M
    if highest <= _HEIGHT_MARGIN_M:
        raise GeometryError(
            "no room for a height spread between the floor and the LEDs",
            field="impairments.height_sd_m",
        )
    drawn = nominal + sd_m * gen.standard_normal(count)
    return np.asarray(np.clip(drawn, _HEIGHT_MARGIN_M, highest))


def _normals(max_deg: float, count: int, gen: np.random.Generator) -> FloatArray:
    if max_deg == 0:
        return np.tile(np.array([0.0, 0.0, 1.0]), (count, 1))
    polar = np.radians(gen.uniform(0.0, max_deg, count))
    azimuth = gen.uniform(0.0, 2 * math.pi, count)
    return np.column_stack(
        (np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar))
    )
