"""People walking in a room, and what their terminals measure along the way.

:func:`random_waypoint_paths` walks each person from one random point of the room to the next
at a fixed speed, pausing between legs; :func:`crossing_paths` sends two people towards each
other along the room so that they pass close by. :func:`simulate_walk` draws the room's and the
terminals' impairments once (as :func:`~app.vlp.simulation.simulate_terminals` does for one
instant) and measures every step of the paths, optionally with shadowing: now and then a hand
or a body blocks a terminal's strongest LED for one fix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..channel import channel_gains, los_gains
from ..errors import GeometryError
from ..layout import Layout
from ..reflections import diffuse_gains
from ..rng import RandomState, as_generator
from ..typing import BoolArray, FloatArray
from .impairments import Impairments
from .terminals import (
    TRUE_ELEMENT_SIZE_M,
    _heights,
    _lognormal,
    _nominal_noise_std,
    _normals,
    _true_layout,
)

__all__ = [
    "SimulatedWalk",
    "WalkerPaths",
    "crossing_paths",
    "random_waypoint_paths",
    "simulate_walk",
]


@dataclass(frozen=True)
class WalkerPaths:
    """Where K people are at T instants.

    Attributes
    ----------
    times_s : ndarray of shape (T,), seconds from the start
    positions : ndarray of shape (T, K, 2), metres
    walking : ndarray of shape (T, K), bool
        Whether each person is moving at that instant (False while paused).
    """

    times_s: FloatArray
    positions: FloatArray
    walking: BoolArray


def random_waypoint_paths(
    layout: Layout,
    count: int,
    *,
    duration_s: float,
    rate_hz: float,
    speed_mps: float = 1.4,
    accel_mps2: float = 2.0,
    pause_s: tuple[float, float] = (2.0, 8.0),
    margin_m: float = 0.3,
    rng: RandomState = None,
) -> WalkerPaths:
    """Random-waypoint walkers: each starts standing at a random point for a random pause,
    walks straight to another random point at ``speed_mps``, pauses, and so on. Each leg
    speeds up and slows down at ``accel_mps2`` (people reach walking speed within a step
    or two, not at once).

    Parameters
    ----------
    layout : Layout
    count : int
        K, the number of people.
    duration_s : float
        Length of the paths, seconds.
    rate_hz : float
        Instants per second.
    speed_mps : float, default=1.4
        Walking speed, m/s.
    accel_mps2 : float, default=2.0
        Acceleration at the start and end of each leg, m/s^2.
    pause_s : (float, float), default=(2, 8)
        Range of the uniform pause between legs, seconds.
    margin_m : float, default=0.3
        Distance the waypoints keep from the walls, metres.
    rng : Generator, int or None

    Returns
    -------
    WalkerPaths
    """
    if not (count >= 1 and duration_s > 0 and rate_hz > 0 and speed_mps > 0):
        raise GeometryError(
            "count, duration_s, rate_hz and speed_mps must be positive", field="walkers"
        )
    gen = as_generator(rng)
    low = np.array([margin_m, margin_m])
    high = np.array([layout.room.length - margin_m, layout.room.width - margin_m])
    times = np.arange(round(duration_s * rate_hz)) / rate_hz
    positions = np.zeros((times.size, count, 2))
    walking = np.zeros((times.size, count), dtype=bool)
    for k in range(count):
        # Legs as (start time, start point, end point, duration); pauses in between.
        here = gen.uniform(low, high)
        clock = gen.uniform(*pause_s)
        legs = []
        while clock < duration_s:
            there = gen.uniform(low, high)
            seconds = _leg_seconds(float(np.linalg.norm(there - here)), speed_mps, accel_mps2)
            legs.append((clock, here, there, seconds))
            clock += seconds + gen.uniform(*pause_s)
            here = there
        positions[:, k] = legs[0][1] if legs else here
        for start, begin, end, seconds in legs:
            during = (times >= start) & (times < start + seconds)
            length = float(np.linalg.norm(end - begin))
            covered = _leg_distance(times[during] - start, length, speed_mps, accel_mps2)
            fraction = covered / max(length, 1e-12)
            positions[during, k] = begin + fraction[:, None] * (end - begin)
            walking[during, k] = True
            positions[times >= start + seconds, k] = end
    return WalkerPaths(times_s=times, positions=positions, walking=walking)


def _leg_seconds(length_m: float, speed_mps: float, accel_mps2: float) -> float:
    """Duration of a leg of ``length_m`` with a trapezoidal (or triangular) speed profile."""
    ramp_m = speed_mps**2 / accel_mps2
    if length_m <= ramp_m:
        return 2.0 * float(np.sqrt(length_m / accel_mps2))
    return speed_mps / accel_mps2 + length_m / speed_mps


def _leg_distance(
    elapsed_s: FloatArray, length_m: float, speed_mps: float, accel_mps2: float
) -> FloatArray:
    """Distance covered ``elapsed_s`` into a leg (see :func:`_leg_seconds`), metres."""
    total = _leg_seconds(length_m, speed_mps, accel_mps2)
    peak = min(speed_mps, float(np.sqrt(length_m * accel_mps2)))
    ramp_s = peak / accel_mps2
    t = np.clip(elapsed_s, 0.0, total)
    rising = 0.5 * accel_mps2 * np.minimum(t, ramp_s) ** 2
    cruising = peak * np.clip(t - ramp_s, 0.0, total - 2.0 * ramp_s)
    falling_t = np.clip(t - (total - ramp_s), 0.0, ramp_s)
    falling = peak * falling_t - 0.5 * accel_mps2 * falling_t**2
    return np.asarray(np.minimum(rising + cruising + falling, length_m))


def crossing_paths(
    layout: Layout,
    *,
    duration_s: float,
    rate_hz: float,
    speed_mps: float = 1.4,
    accel_mps2: float = 2.0,
    separation_m: float = 0.5,
    stand_s: float = 3.0,
    margin_m: float = 0.5,
) -> WalkerPaths:
    """Two people on parallel lines ``separation_m`` apart along the room's length, walking
    towards each other from opposite ends (they pass mid-room), standing ``stand_s`` at each
    end before turning back. Each leg speeds up and slows down at ``accel_mps2``, as the
    waypoint walkers' do (no one goes from standing to 1.4 m/s within one fix).

    Returns
    -------
    WalkerPaths
        K = 2.
    """
    times = np.arange(round(duration_s * rate_hz)) / rate_hz
    middle = layout.room.width / 2.0
    ends = (margin_m, layout.room.length - margin_m)
    length = ends[1] - ends[0]
    leg_s = _leg_seconds(length, speed_mps, accel_mps2)
    period = 2.0 * (leg_s + stand_s)
    phase = np.mod(times, period)
    # 0..1 along the room: stand, walk out, stand, walk back.
    out = _leg_distance(phase - stand_s, length, speed_mps, accel_mps2) / length
    back = _leg_distance(phase - 2.0 * stand_s - leg_s, length, speed_mps, accel_mps2) / length
    along = out - back
    walking = ((phase > stand_s) & (phase < stand_s + leg_s)) | (phase > 2.0 * stand_s + leg_s)
    first = ends[0] + along * length
    second = ends[1] - along * length
    positions = np.stack(
        (
            np.column_stack((first, np.full(times.size, middle - separation_m / 2.0))),
            np.column_stack((second, np.full(times.size, middle + separation_m / 2.0))),
        ),
        axis=1,
    )
    return WalkerPaths(
        times_s=times, positions=positions, walking=np.column_stack((walking, walking))
    )


@dataclass(frozen=True)
class SimulatedWalk:
    """What K walking terminals measured at T instants.

    Attributes
    ----------
    amplitudes : ndarray of shape (T, K, M)
        Noisy per-terminal pilot amplitudes.
    shadowed : ndarray of shape (T, K), bool
        Fixes whose strongest LED was blocked.
    true_layout : Layout
        The room as it really is (drawn once for the whole walk).
    noise_std : float
    """

    amplitudes: FloatArray
    shadowed: BoolArray
    true_layout: Layout
    noise_std: float


def simulate_walk(
    layout: Layout,
    positions: FloatArray,
    impairments: Impairments,
    *,
    snr_db: float,
    shadowing_probability: float = 0.0,
    rng: RandomState = None,
) -> SimulatedWalk:
    """Amplitudes of K terminals along their paths, in one draw of the room's impairments.

    Parameters
    ----------
    layout : Layout
        The room as the service knows it.
    positions : ndarray of shape (T, K, 2)
        True ``(x, y)`` of each terminal at each instant, metres.
    impairments : Impairments
        Drawn once: LED tolerances for the room, gain, height and tilt per terminal.
    snr_db : float
        As for :func:`~app.vlp.simulation.simulate_terminals`.
    shadowing_probability : float, default=0
        Chance that a fix has its strongest LED blocked (that amplitude is noise only).
    rng : Generator, int or None

    Returns
    -------
    SimulatedWalk
    """
    if not 0.0 <= shadowing_probability <= 1.0:
        raise GeometryError(
            f"shadowing_probability must be in [0, 1], got {shadowing_probability!r}",
            field="shadowing_probability",
        )
    gen = as_generator(rng)
    path = np.asarray(positions, dtype=np.float64)
    steps, count = path.shape[:2]
    true_layout = _true_layout(layout, impairments, gen)
    gains = _lognormal(gen, impairments.gain_sd, count)
    heights = np.tile(_heights(layout, impairments.height_sd_m, count, gen), steps)
    normals = np.tile(_normals(impairments.tilt_max_deg, count, gen), (steps, 1))
    points = path.reshape(-1, 2)
    xyz = np.column_stack((points, heights))
    if impairments.height_sd_m == 0 and impairments.tilt_max_deg == 0:
        channel = channel_gains(true_layout, points)
    else:
        channel = los_gains(true_layout, xyz, normals)
    if impairments.reflectance is not None:
        channel = channel + diffuse_gains(
            true_layout, xyz, normals, element_size_m=TRUE_ELEMENT_SIZE_M
        )
    clean = (channel * true_layout.pilot_amplitudes[:, None]).T.reshape(steps, count, -1)
    clean = clean * (gains * impairments.common_scale)[None, :, None]
    shadowed = gen.random((steps, count)) < shadowing_probability
    strongest = np.argmax(clean, axis=2)
    t_index, k_index = np.nonzero(shadowed)
    clean[t_index, k_index, strongest[t_index, k_index]] = 0.0
    noise_std = _nominal_noise_std(layout, snr_db)
    amplitudes = clean + noise_std * gen.standard_normal(clean.shape)
    return SimulatedWalk(
        amplitudes=amplitudes, shadowed=shadowed, true_layout=true_layout, noise_std=noise_std
    )
