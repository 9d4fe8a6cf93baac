"""What the Massey survey itself allows a K = 1 fix: its noise, how well a beam of any
rotationally symmetric shape explains it, the Cramer-Rao bound, and what a survey of about one
point per square metre supports with a Lambertian beam and with a measured (tabulated) one.

    python -m bench.measured_floor DATA --commit 58d0c0f608de561901dec29a2f0ebe055c117f84

DATA is a fetched copy of the survey (``bench._massey``). The figures, all from the data alone
(no service):

- repeat noise: readings of points less than 1.5 cm apart (both detected) differ by a
  multiplicative noise; its standard deviation in log units, and the absolute one by level;
- radial profiles: each LED's log reading as a cubic spline of the horizontal distance, fitted
  to every point: what any rotationally symmetric beam (a luminaire's tabulated photometry) can
  explain, against the repeat noise;
- the Cramer-Rao bound of a fix at each test point from its detected LEDs, with those profiles
  as the true model and the repeat noise (receiver gain known, and free);
- a dense fingerprint: weighted kNN (k = 4) over every other point of the survey, 150 times
  the facility survey's density;
- the maximum-likelihood fix (log readings, detected LEDs) on a grid, with each LED's beam
  fitted to the facility's survey points only: a Lambertian beam (scale and order) and a radial
  profile.

The test points and the facility survey are those of ``bench.measured`` (same seed).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from scipy.interpolate import BSpline, make_lsq_spline
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from app.vlp.typing import FloatArray, IntArray
from bench._common import REPO_ROOT, machine_markdown, machine_record
from bench._massey import (
    MasseySurvey,
    estimate_receiver_height,
    facility_split,
    load_survey,
    shown_command,
    weighted_knn,
)

__all__ = [
    "LambertianBeams",
    "RadialProfiles",
    "angular_profile",
    "bound_errors",
    "grid_fixes",
    "horizontal_distances",
    "leave_one_out_knn",
    "main",
    "repeat_noise",
]

# Points closer than this are taken as the same place (the log readings' spatial change over
# it is about 1 %, a tenth of the noise).
SAME_PLACE_M = 0.015
# Inner knots (m of horizontal distance) of the facility survey's radial profiles: the
# survey has tens of points per LED, so few knots.
SURVEY_KNOTS_M = (1.5, 3.0)
DENSE_KNOTS_M = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
# Beyond the farthest distance fitted, a profile falls at least this fast (log units per m).
MIN_TAIL_SLOPE = 0.5
COARSE_STEP_M = 0.05
FINE_STEP_M = 0.01

# (figure, median cm, mean cm, p95 cm) and (low level, high level, sd, pairs)
Row = tuple[str, float, float, float]
LevelRow = tuple[float, float, float, int]


class Beams(Protocol):
    """Every LED's log reading as a function of the horizontal distance."""

    def log_model(self, distances: FloatArray) -> FloatArray:
        """(..., M) log readings at horizontal distances (..., M)."""
        ...


def horizontal_distances(points: FloatArray, leds: FloatArray) -> FloatArray:
    """(n, M) horizontal distance of each point (n, 2) from each LED (M, >= 2)."""
    return np.hypot(points[:, None, 0] - leds[None, :, 0], points[:, None, 1] - leds[None, :, 1])


def repeat_noise(points: FloatArray, readings: FloatArray) -> tuple[float, int, list[LevelRow]]:
    """The readings' noise from pairs of points less than :data:`SAME_PLACE_M` apart.

    Returns the sd of one log reading (from the pairs' log ratios, both detected), the number
    of pairs, and rows ``(low, high, sd, count)`` of one reading's absolute sd by level.
    """
    pairs = np.array(sorted(cKDTree(points).query_pairs(SAME_PLACE_M)), dtype=np.int64)
    if len(pairs) == 0:
        return math.nan, 0, []
    first, second = readings[pairs[:, 0]], readings[pairs[:, 1]]
    both = np.isfinite(first) & np.isfinite(second)
    log_sd = float(np.std(np.log(first[both] / second[both])) / math.sqrt(2.0))
    level, difference = (first[both] + second[both]) / 2.0, first[both] - second[both]
    rows: list[LevelRow] = []
    for low, high in ((0, 50), (50, 150), (150, 400), (400, math.inf)):
        chosen = (level >= low) & (level < high)
        if chosen.sum() >= 10:
            rows.append(
                (low, high, float(np.std(difference[chosen]) / math.sqrt(2.0)), int(chosen.sum()))
            )
    return log_sd, len(pairs), rows


@dataclass(frozen=True)
class RadialProfiles:
    """Each LED's log reading as a cubic spline of horizontal distance (a rotationally
    symmetric beam of any shape, seen by a level receiver at one height)."""

    splines: tuple[BSpline, ...]
    ranges: FloatArray  # (M, 2): distances fitted
    tail_slopes: FloatArray  # (M,)

    @classmethod
    def fit(
        cls, distances: FloatArray, readings: FloatArray, knots: Sequence[float]
    ) -> RadialProfiles:
        """Least squares on the detected log readings; ``distances`` and ``readings`` (n, M)."""
        splines, ranges, tails = [], [], []
        for led in range(readings.shape[1]):
            seen = np.isfinite(readings[:, led])
            order = np.argsort(distances[seen, led])
            x, y = distances[seen, led][order], np.log(readings[seen, led][order])
            inner = [t for t in knots if x[0] + 0.05 < t < x[-1] - 0.05]
            spline = make_lsq_spline(x, y, np.r_[[x[0]] * 4, inner, [x[-1]] * 4], k=3)
            splines.append(spline)
            ranges.append((x[0], x[-1]))
            tails.append(min(float(spline.derivative()(x[-1])), -MIN_TAIL_SLOPE))
        return cls(tuple(splines), np.array(ranges), np.array(tails))

    def log_model(self, distances: FloatArray) -> FloatArray:
        """Log readings (..., M) at horizontal distances (..., M); linear beyond the data."""
        out = np.empty_like(distances)
        for led, spline in enumerate(self.splines):
            r = distances[..., led]
            low, high = self.ranges[led]
            out[..., led] = spline(np.clip(r, low, high)) + np.where(
                r > high, (r - high) * self.tail_slopes[led], 0.0
            )
        return out

    def slopes(self, distances: FloatArray) -> FloatArray:
        """d log reading / d distance (..., M)."""
        out = np.empty_like(distances)
        for led, spline in enumerate(self.splines):
            r = distances[..., led]
            low, high = self.ranges[led]
            inside = spline.derivative()(np.clip(r, low, high))
            out[..., led] = np.where(
                r > high, self.tail_slopes[led], np.where(r < low, 0.0, inside)
            )
        return out


@dataclass(frozen=True)
class LambertianBeams:
    """Each LED a Lambertian source (its own log scale and order) over a level receiver
    ``drop`` metres below it: ``log a = s + (m + 1) log dz - (m + 3) / 2 log(dz^2 + r^2)``."""

    log_scales: FloatArray
    orders: FloatArray
    drop: float

    @classmethod
    def fit(cls, distances: FloatArray, readings: FloatArray, drop: float) -> LambertianBeams:
        """Least squares on the detected log readings."""
        scales, orders = [], []
        for led in range(readings.shape[1]):
            seen = np.isfinite(readings[:, led])
            r, y = distances[seen, led], np.log(readings[seen, led])

            def residual(theta: FloatArray, r: FloatArray = r, y: FloatArray = y) -> FloatArray:
                return _lambertian(r, theta[0], theta[1], drop) - y

            fit = least_squares(residual, [float(y.max()) + 3.0 * math.log(drop), 1.0])
            scales.append(fit.x[0])
            orders.append(fit.x[1])
        return cls(np.array(scales), np.array(orders), drop)

    def log_model(self, distances: FloatArray) -> FloatArray:
        return _lambertian(distances, self.log_scales, self.orders, self.drop)


def _lambertian(r: FloatArray, scale: FloatArray, order: FloatArray, drop: float) -> FloatArray:
    return np.asarray(
        scale + (order + 1) * math.log(drop) - (order + 3) / 2 * np.log(drop * drop + r * r)
    )


def bound_errors(
    profiles: RadialProfiles,
    leds: FloatArray,
    points: FloatArray,
    detected: np.ndarray,
    log_sd: float,
    *,
    free_gain: bool,
    draws: int = 200,
    seed: int = 0,
) -> FloatArray:
    """Errors (n * draws,) drawn from each point's Cramer-Rao bound: the Fisher information
    of its detected log readings (independent, sd ``log_sd``) about its position (and a
    common log gain when ``free_gain``)."""
    rng = np.random.default_rng(seed)
    distances = horizontal_distances(points, leds)
    slopes = profiles.slopes(distances)
    out = []
    for index in range(len(points)):
        seen = np.flatnonzero(detected[index])
        away = (points[index] - leds[seen, :2]) / np.maximum(distances[index, seen], 1e-9)[:, None]
        rows = slopes[index, seen, None] * away
        if free_gain:
            rows = np.c_[rows, np.ones(len(seen))]
        information = rows.T @ rows / log_sd**2
        covariance = np.linalg.pinv(information)[:2, :2]
        out.append(np.hypot(*rng.multivariate_normal(np.zeros(2), covariance, size=draws).T))
    return np.concatenate(out)


def grid_fixes(
    beams: Beams,
    leds: FloatArray,
    readings: FloatArray,
    bounds: tuple[FloatArray, FloatArray],
    *,
    free_gain: bool,
) -> FloatArray:
    """Maximum-likelihood positions (n, 2): least squares of the detected log readings
    against ``beams`` on a coarse grid over
    ``bounds``, then a fine grid around the best coarse point; with ``free_gain`` the
    residuals' mean (a common log gain) is removed first."""
    model = beams.log_model
    low, high = bounds

    def grid(lo: FloatArray, hi: FloatArray, step: float) -> FloatArray:
        axes = [np.arange(lo[i], hi[i] + step / 2, step) for i in range(2)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)

    coarse = grid(low, high, COARSE_STEP_M)
    coarse_model = model(horizontal_distances(coarse, leds))
    out = np.empty((len(readings), 2))
    for index, reading in enumerate(readings):
        seen = np.isfinite(reading)
        best = coarse[_best(coarse_model, np.log(reading[seen]), seen, free_gain)]
        fine = grid(best - 2 * COARSE_STEP_M, best + 2 * COARSE_STEP_M, FINE_STEP_M)
        fine_model = model(horizontal_distances(fine, leds))
        out[index] = fine[_best(fine_model, np.log(reading[seen]), seen, free_gain)]
    return out


def _best(model: FloatArray, observed: FloatArray, seen: np.ndarray, free_gain: bool) -> int:
    residual = observed - model[:, seen]
    if free_gain:
        residual = residual - residual.mean(axis=1, keepdims=True)
    return int(np.argmin((residual**2).sum(axis=1)))


def leave_one_out_knn(survey: MasseySurvey, test: IntArray, k: int = 4) -> FloatArray:
    """Positions (n, 2) of the points ``test`` by weighted kNN (as :func:`weighted_knn`) over
    every other point of the survey."""
    logs = np.log(np.nan_to_num(survey.readings, nan=survey.floor))
    distance, nearest = cKDTree(logs).query(logs[test], k=k + 1)
    keep = nearest != np.asarray(test)[:, None]
    # the point itself is among the k + 1 nearest (at distance 0): drop it, keep k others
    order = np.argsort(~keep, axis=1, kind="stable")[:, :k]
    distance = np.take_along_axis(distance, order, axis=1)
    nearest = np.take_along_axis(nearest, order, axis=1)
    weights = 1.0 / (distance + 1e-9)
    weights /= weights.sum(axis=1, keepdims=True)
    return np.asarray(np.einsum("nk,nkd->nd", weights, survey.points[nearest]))


def angular_profile(survey: MasseySurvey, drop: float) -> tuple[FloatArray, FloatArray]:
    """Each LED's intensity by angle off its axis, relative to its mean within 20 degrees
    (medians over the LEDs): the reading times ``d^2`` over the receiver's ``cos`` (a level
    receiver ``drop`` below the LEDs). Bins of 5 degrees from 0 to 75; NaN where too few
    readings."""
    r = horizontal_distances(survey.points, survey.leds)
    d2 = r * r + drop * drop
    cosine = drop / np.sqrt(d2)
    intensity = survey.readings * d2 / cosine
    angle = np.degrees(np.arccos(cosine))
    edges = np.arange(0.0, 80.0, 5.0)
    relative = np.full((survey.readings.shape[1], len(edges)), np.nan)
    for led in range(survey.readings.shape[1]):
        seen = np.isfinite(intensity[:, led])
        axis = seen & (angle[:, led] < 20.0)
        if axis.sum() < 8:
            continue
        reference = np.median(intensity[axis, led])
        for column, low in enumerate(edges):
            chosen = seen & (angle[:, led] >= low) & (angle[:, led] < low + 5.0)
            if chosen.sum() >= 8:
                relative[led, column] = np.median(intensity[chosen, led]) / reference
    medians = [np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in relative.T]
    return edges, np.array(medians)


def _stats(errors_m: FloatArray) -> tuple[float, float, float]:
    cm = 100.0 * np.asarray(errors_m)
    return (
        round(float(np.median(cm)), 2),
        round(float(cm.mean()), 2),
        round(float(np.percentile(cm, 95)), 1),
    )


def run(survey: MasseySurvey, *, max_test: int, seed: int) -> tuple[list[Row], dict[str, Any]]:
    """Every figure: rows ``(figure, median cm, mean cm, p95 cm)`` and the page's facts."""
    split = facility_split(survey.points, seed=seed, max_test=max_test)
    test, facility = split.test, split.survey
    log_sd, n_pairs, by_level = repeat_noise(survey.points, survey.readings)
    distances = horizontal_distances(survey.points, survey.leds)
    dense = RadialProfiles.fit(distances, survey.readings, DENSE_KNOTS_M)
    dense_residual = np.log(survey.readings) - dense.log_model(distances)
    residual_sd = np.sqrt(np.nanmean(dense_residual**2, axis=0))
    truth, readings = survey.points[test], survey.readings[test]
    rows: list[Row] = []
    for free_gain in (False, True):
        errors = bound_errors(
            dense, survey.leds, truth, np.isfinite(readings), log_sd, free_gain=free_gain, seed=seed
        )
        rows.append((f"Cramer-Rao bound, gain {'free' if free_gain else 'known'}", *_stats(errors)))
    dense_knn = leave_one_out_knn(survey, test)
    rows.append(
        ("weighted kNN, every other point as reference", *_stats(np.hypot(*(dense_knn - truth).T)))
    )
    knn = weighted_knn(survey.points[facility], survey.readings[facility], readings)
    knn_stats = _stats(np.hypot(*(knn - truth).T))
    rows.append(("weighted kNN, facility survey", *knn_stats))
    bounds = (survey.points.min(axis=0), survey.points.max(axis=0))
    drop = (
        float(np.mean(survey.leds[:, 2]))
        - estimate_receiver_height(survey, facility, np.round(np.arange(0.0, 1.51, 0.1), 2))[0]
    )
    fitted: dict[str, Beams] = {
        "Lambertian beams": LambertianBeams.fit(
            distances[facility], survey.readings[facility], drop
        ),
        "radial profiles": RadialProfiles.fit(
            distances[facility], survey.readings[facility], SURVEY_KNOTS_M
        ),
    }
    for name, beam in fitted.items():
        for free_gain in (False, True):
            found = grid_fixes(beam, survey.leds, readings, bounds, free_gain=free_gain)
            label = f"fix, {name} from the facility survey, gain {'free' if free_gain else 'known'}"
            rows.append((label, *_stats(np.hypot(*(found - truth).T))))
    info = {
        "log_sd": log_sd,
        "pairs": n_pairs,
        "by_level": by_level,
        "residual_sd": residual_sd,
        "test_points": len(test),
        "facility_points": len(facility),
        "knn_median": knn_stats[0],
        "drop": drop,
        "angular_profile": angular_profile(survey, drop),
    }
    return rows, info


def write_page(rows: list[Row], info: dict[str, Any], command: str, page: Path, data: Path) -> None:
    """The results page and its CSV."""
    data.parent.mkdir(parents=True, exist_ok=True)
    with data.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["figure", "median_cm", "mean_cm", "p95_cm"])
        writer.writerows(rows)
    table = "\n".join(
        ["| figure | median cm | mean cm | p95 cm |", "|---|---|---|---|"]
        + [f"| {name} | {median} | {mean} | {p95} |" for name, median, mean, p95 in rows]
    )
    levels = "\n".join(
        ["| reading level | sd of one reading | pairs |", "|---|---|---|"]
        + [
            f"| {low:g}-{high:g} | {sd:.1f} | {count} |"
            for low, high, sd, count in info["by_level"]
        ]
    )
    edges, relative = info["angular_profile"]
    # a Lambertian beam of 60 degrees' half power (order 1), relative to its mean within 20
    lambertian = np.cos(np.radians(edges + 2.5)) / np.mean(np.cos(np.radians(np.arange(0.5, 20.0))))
    angles = "\n".join(
        [
            "| degrees off the axis | " + " | ".join(f"{e:g}-{e + 5:g}" for e in edges) + " |",
            "|---" * (len(edges) + 1) + "|",
            "| measured | "
            + " | ".join("-" if np.isnan(v) else f"{v:.2f}" for v in relative)
            + " |",
            "| Lambertian, 60 degrees | " + " | ".join(f"{v:.2f}" for v in lambertian) + " |",
        ]
    )
    residuals = ", ".join(f"{value:.3f}" for value in info["residual_sd"])
    target = 0.3 * info["knn_median"]
    text = f"""# What the measured survey allows a single fix

Generated by `{command}` (CSV: `docs/data/measured_floor.csv`).

The data alone, no service: the Massey lobby survey of [measured rooms](measured.md), its
{info["test_points"]} test points and its facility survey of {info["facility_points"]} points.
What the columns mean is in the module docstring of `bench/measured_floor.py`.

## The noise

{info["pairs"]} pairs of points less than 1.5 cm apart: one log reading scatters with sd
**{info["log_sd"]:.3f}** (a multiplicative noise of about {100 * info["log_sd"]:.0f} %); in
absolute units the scatter grows with the level:

{levels}

Each LED's radial profile fitted to every point of the survey leaves residuals of sd (log
units, per LED) {residuals}: a rotationally symmetric beam explains the readings down to about
the repeat noise. The beams are not Lambertian: each LED's intensity by the angle off its axis
(the reading times the squared distance over the receiver's cosine, receiver
{info["drop"]:.2f} m below the LEDs, relative to within 20 degrees; the median over the LEDs)
against the Lambertian beam the layouts specify:

{angles}

A Lambertian order can only fit such a beam as a half-power angle near 90 degrees. (Beyond
about 65 degrees most readings are below the detector's floor and only the strongest are
left, so those bins read high.)

## Single fixes

{table}

A fix three times better than the facility kNN's median would be {target:.1f} cm; the
Cramer-Rao bound with a perfect beam model sits {"just below" if rows[0][1] < target else "above"}
it, so only an efficient fix on an almost exact beam could reach it. The service's own fixes
on this survey are in [measured rooms](measured.md). Fitting each beam's measured shape
(a radial profile) rather than a Lambertian order to the same facility survey removes much of
the gap between the Lambertian fit and the bound.

Machine:

{machine_markdown(machine_record())}
"""
    page.parent.mkdir(parents=True, exist_ok=True)
    page.write_text(text, encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: see the module docstring."""
    parser = argparse.ArgumentParser(prog="python -m bench.measured_floor", description=__doc__)
    parser.add_argument("data", type=Path, help="fetched copy (directory or bare git dir)")
    parser.add_argument("--commit", default=None, help="commit to read from a git directory")
    parser.add_argument("--max-test", type=int, default=600, help="test points")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="default: docs/ (full run)")
    args = parser.parse_args(argv)
    survey = load_survey(args.data, args.commit)
    rows, info = run(survey, max_test=args.max_test, seed=args.seed)
    given = sys.argv[1:] if argv is None else argv
    command = shown_command("python -m bench.measured_floor", given, args.data)
    page = (args.out or REPO_ROOT / "docs" / "results") / "measured-floor.md"
    data = (args.out or REPO_ROOT / "docs" / "data") / "measured_floor.csv"
    write_page(rows, info, command, page, data)
    for row in rows:
        print(*row, sep=" | ")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
