"""The tracking benchmark's runs: walkers simulated, raw fixes solved, fixes tracked, scored.

One :class:`Scenario` is a room, how it really differs from its layout, how the walkers'
measurements reach the service (their own labelled amplitudes, or K of them aggregated into
one correlation matrix), and whether a hand or a body shadows a fix now and then. Raw fixes
come from the service's own solver (``make_solver("gridless", ...)``, labelled fixes through
``solve_terminals`` as the service does); tracks from :mod:`app.vlp.tracking`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cache

import numpy as np
from scipy.optimize import linear_sum_assignment

from app.vlp.fingerprints import Fingerprint, build_fingerprint
from app.vlp.layout import Layout
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.radii import confidence_radii
from app.vlp.simulation import (
    Impairments,
    WalkerPaths,
    crossing_paths,
    random_waypoint_paths,
    simulate_walk,
)
from app.vlp.solvers import Solution, make_solver
from app.vlp.solvers.gridless import GridlessSolver
from app.vlp.tracking import (
    CONFIRMED,
    TrackerSettings,
    Tracks,
    age_tracks,
    estimates,
    gospa,
    step_anonymous,
    step_labelled,
)
from app.vlp.typing import FloatArray, IntArray

from .rooms import hall_layout

__all__ = ["CLOSE_PASS_M", "ROOMS", "Outcome", "Scenario", "correspondences", "run_scenario"]

RATE_HZ = 5.0
SNR_DB = 30.0
SHADOWING = 0.05
GOSPA_CUTOFF_M = 1.0
# When the lag after a start is read: the along-track shortfall over this window after it.
LAG_WINDOW_S = (0.4, 2.0)
MIX = Impairments.realistic_mix()


@dataclass(frozen=True)
class Room:
    """A benchmark room: the layout the service knows and how the real room differs."""

    name: str
    layout: Layout
    impairments: Impairments


def _with_reflectance(layout: Layout) -> Layout:
    room = dataclasses.replace(layout.room, reflectance=MIX.reflectance)
    return dataclasses.replace(layout, room=room)


ROOMS = {
    "paper": Room("paper", paper_layout(), Impairments.ideal()),
    "mix": Room("realistic mix", _with_reflectance(paper_layout()), MIX),
    "hall": Room("hall", hall_layout(), Impairments.ideal()),
}


@dataclass(frozen=True)
class Scenario:
    """One cell of the results: room, mode (``terminals`` or ``correlation``), K, shadowing
    and the paths (``waypoints`` or ``crossing``)."""

    room: str
    mode: str
    walkers: int
    shadowing: bool
    paths: str = "waypoints"


@dataclass
class Outcome:
    """What a scenario measured (errors in metres, lag in seconds)."""

    scenario: Scenario
    raw_walking: list[float] = field(default_factory=list)
    tracked_walking: list[float] = field(default_factory=list)
    raw_standing: list[float] = field(default_factory=list)
    tracked_standing: list[float] = field(default_factory=list)
    averaged_standing: list[float] = field(default_factory=list)
    unshadowed_standing: list[float] = field(default_factory=list)
    covered: list[bool] = field(default_factory=list)
    lags_s: list[float] = field(default_factory=list)
    gospa_raw: list[tuple[float, float, float, float]] = field(default_factory=list)
    gospa_tracked: list[tuple[float, float, float, float]] = field(default_factory=list)
    switches: int = 0
    close_passes: int = 0
    walked_m: float = 0.0


@cache
def _fingerprint(room: str) -> Fingerprint:
    return build_fingerprint(ROOMS[room].layout)


@cache
def _solver(room: str, model: str) -> GridlessSolver:
    solver = make_solver("gridless", _fingerprint(room), "correlation" if model else "power")
    assert isinstance(solver, GridlessSolver)
    return solver


def _paths(scenario: Scenario, duration_s: float, seed: int) -> WalkerPaths:
    layout = ROOMS[scenario.room].layout
    if scenario.paths == "crossing":
        return crossing_paths(layout, duration_s=duration_s, rate_hz=RATE_HZ)
    return random_waypoint_paths(
        layout, scenario.walkers, duration_s=duration_s, rate_hz=RATE_HZ, rng=seed
    )


def _fix(scenario: Scenario, amplitudes: FloatArray) -> Solution:
    solver = _solver(scenario.room, "correlation")
    if scenario.mode == "terminals":
        return solver.solve_terminals(amplitudes)
    measurement = measurement_from_amplitudes(amplitudes, "correlation", amplitudes.shape[1])
    return solver.solve(measurement, amplitudes.shape[0])


def run_scenario(
    scenario: Scenario,
    *,
    duration_s: float,
    seed: int,
    settings: TrackerSettings | None = None,
) -> Outcome:
    """Simulate, solve and track one scenario; the errors and scores it produced."""
    settings = settings or TrackerSettings()
    room = ROOMS[scenario.room]
    paths = _paths(scenario, duration_s, seed)
    walk = simulate_walk(
        room.layout,
        paths.positions,
        room.impairments,
        snr_db=SNR_DB,
        shadowing_probability=SHADOWING if scenario.shadowing else 0.0,
        rng=seed + 1,
    )
    outcome = Outcome(scenario)
    tracks = Tracks.empty()
    ids: IntArray = np.zeros(0, dtype=np.intp)  # a stable id per track row
    next_id = 0
    labelled_rows = np.full(paths.positions.shape[1], -1, dtype=np.intp)
    tracked_path = np.full(paths.positions.shape, np.nan)
    raw_path = np.full(paths.positions.shape, np.nan)
    raw_cov_path = np.tile(np.eye(2), (*paths.positions.shape[:2], 1, 1))
    last_owner: dict[int, int] = {}
    for step, time_s in enumerate(paths.times_s):
        truth = paths.positions[step]
        solution = _fix(scenario, walk.amplitudes[step])
        raw = solution.positions
        raw_cov = _covariances(solution)
        if scenario.mode == "terminals":
            result = step_labelled(tracks, labelled_rows, raw, raw_cov, float(time_s), settings)
        else:
            result = step_anonymous(tracks, raw, raw_cov, float(time_s), settings)
        tracks = result.tracks
        new = tracks.size - ids.size
        ids = np.concatenate((ids, next_id + np.arange(new)))
        next_id += new
        status, removed = age_tracks(tracks, float(time_s), settings)
        tracks = dataclasses.replace(tracks, status=status)
        mean, covariance = estimates(tracks.bank)
        radius = confidence_radii(covariance[:, :2, :2])
        if scenario.mode == "terminals":
            labelled_rows = result.fix_rows
            own = result.fix_rows
            tracked_path[step] = mean[own, :2]
            raw_path[step] = raw
            raw_cov_path[step] = raw_cov
            _score_labelled(outcome, truth, raw, mean[own, :2], radius[own], paths.walking[step])
        else:
            shown = (status == CONFIRMED) & ~removed
            _score_anonymous(outcome, truth, raw, mean[shown, :2], ids[shown], last_owner)
        keep = ~removed
        if not np.all(keep):
            tracks = tracks.take(keep)
            ids = ids[keep]
    if scenario.mode == "terminals":
        outcome.lags_s = _lags(paths, tracked_path)
        outcome.averaged_standing = _averaged_standing(paths, raw_path, raw_cov_path)
        outcome.unshadowed_standing = _averaged_standing(
            paths, raw_path, raw_cov_path, ~walk.shadowed
        )
    else:
        outcome.close_passes = _close_passes(paths)
    steps = np.linalg.norm(np.diff(paths.positions, axis=0), axis=2)
    outcome.walked_m = float(np.sum(steps))
    return outcome


def _covariances(solution: Solution) -> FloatArray:
    if solution.covariances is None:
        raise AssertionError("the gridless solver gives every estimate a covariance")
    return np.asarray(solution.covariances)


def _score_labelled(
    outcome: Outcome,
    truth: FloatArray,
    raw: FloatArray,
    tracked: FloatArray,
    radius: FloatArray,
    walking: np.ndarray,
) -> None:
    raw_error = np.linalg.norm(raw - truth, axis=1)
    tracked_error = np.linalg.norm(tracked - truth, axis=1)
    for k in range(truth.shape[0]):
        if walking[k]:
            outcome.raw_walking.append(float(raw_error[k]))
            outcome.tracked_walking.append(float(tracked_error[k]))
        else:
            outcome.raw_standing.append(float(raw_error[k]))
            outcome.tracked_standing.append(float(tracked_error[k]))
        outcome.covered.append(bool(tracked_error[k] <= radius[k]))


def _score_anonymous(
    outcome: Outcome,
    truth: FloatArray,
    raw: FloatArray,
    tracked: FloatArray,
    ids: IntArray,
    last_owner: dict[int, int],
) -> None:
    for found, sink in ((raw, outcome.gospa_raw), (tracked, outcome.gospa_tracked)):
        score = gospa(truth, found, cutoff_m=GOSPA_CUTOFF_M)
        sink.append((score.distance, score.localisation, score.missed, score.false))
    if tracked.shape[0] == 0:
        return
    for walker, track in correspondences(truth, tracked, ids, last_owner).items():
        previous = last_owner.get(walker)
        if previous is not None and previous != track:
            outcome.switches += 1
        last_owner[walker] = track


def correspondences(
    truth: FloatArray, tracked: FloatArray, ids: IntArray, last_owner: dict[int, int]
) -> dict[int, int]:
    """Which track answers for each walker now, as the CLEAR MOT metrics count identity
    switches (Bernardin and Stiefelhagen, EURASIP JIVP 2008): a walker keeps last instant's
    track while it is still within the cut-off; the others are paired by least total
    distance. (Pairing every instant afresh would count two walkers who pass within a few
    centimetres of each other as swapping and swapping back, whatever the tracks did.)"""
    distance = np.linalg.norm(truth[:, None, :] - tracked[None, :, :], axis=2)
    column_of = {int(track): column for column, track in enumerate(ids)}
    pairs: dict[int, int] = {}
    for walker, track in last_owner.items():
        column = column_of.get(track)
        if column is not None and distance[walker, column] < GOSPA_CUTOFF_M:
            pairs[walker] = column
    free_rows = [w for w in range(truth.shape[0]) if w not in pairs]
    free_cols = [c for c in range(tracked.shape[0]) if c not in pairs.values()]
    if free_rows and free_cols:
        sub = distance[np.ix_(free_rows, free_cols)]
        rows, cols = linear_sum_assignment(sub)
        for r, c in zip(rows, cols, strict=True):
            if sub[r, c] < GOSPA_CUTOFF_M:
                pairs[free_rows[r]] = free_cols[c]
    return {walker: int(ids[column]) for walker, column in pairs.items()}


def _lags(paths: WalkerPaths, tracked: FloatArray) -> list[float]:
    """For each start from standing: the mean along-track shortfall of the track behind the
    walker, divided by the walker's speed, over :data:`LAG_WINDOW_S` after the start."""
    lags = []
    times = paths.times_s
    for k in range(paths.positions.shape[1]):
        moving = paths.walking[:, k]
        starts = np.nonzero(moving[1:] & ~moving[:-1])[0] + 1
        for start in starts:
            begin = times[start]
            window = (times >= begin + LAG_WINDOW_S[0]) & (times <= begin + LAG_WINDOW_S[1])
            window &= moving
            if np.count_nonzero(window) < 3:
                continue
            velocity = np.gradient(paths.positions[:, k], times, axis=0)[window]
            speed = np.linalg.norm(velocity, axis=1)
            direction = velocity / speed[:, None]
            behind = np.einsum(
                "ta,ta->t", paths.positions[window, k] - tracked[window, k], direction
            )
            lags.append(float(np.mean(behind / speed)))
    return [lag for lag in lags if math.isfinite(lag)]


# Walkers closer than this are one blob to any tracker without more than positions (about
# a person's width: real people seldom come closer, simulated points do).
CLOSE_PASS_M = 0.3


def _averaged_standing(
    paths: WalkerPaths,
    raw: FloatArray,
    raw_covariances: FloatArray,
    kept: np.ndarray | None = None,
) -> list[float]:
    """Errors of the weighted mean (weights: the inverse of each fix's covariance) of every
    raw fix of each whole pause, at each instant of the pause: what averaging all of a
    pause's fixes, past and future, leaves (an error shared by successive fixes at one place,
    as a layout that does not fit the room gives, does not average out). ``kept`` (T, K):
    only these fixes are averaged (all of a pause where it keeps none), e.g. the unshadowed
    ones, as an estimator that knew which fixes were shadowed could."""
    errors: list[float] = []
    for k in range(paths.positions.shape[1]):
        standing = np.nonzero(~paths.walking[:, k])[0]
        for pause in np.split(standing, np.nonzero(np.diff(standing) > 1)[0] + 1):
            if pause.size == 0:
                continue
            used = pause
            if kept is not None and np.any(kept[pause, k]):
                used = pause[kept[pause, k]]
            weights = np.linalg.inv(raw_covariances[used, k])
            mean = np.linalg.solve(
                weights.sum(axis=0), np.einsum("tab,tb->a", weights, raw[used, k])
            )
            errors += np.linalg.norm(mean - paths.positions[pause, k], axis=1).tolist()
    return errors


def _close_passes(paths: WalkerPaths) -> int:
    """How often two walkers come within :data:`CLOSE_PASS_M` of each other (each approach
    counted once)."""
    count = 0
    walkers = paths.positions.shape[1]
    for a in range(walkers):
        for b in range(a + 1, walkers):
            gap = np.linalg.norm(paths.positions[:, a] - paths.positions[:, b], axis=1)
            close = gap < CLOSE_PASS_M
            count += int(close[0]) + int(np.count_nonzero(close[1:] & ~close[:-1]))
    return count
