"""The Massey University public VLP survey: loading, the facility split and the baselines.

The survey (Glass et al., "Autonomous Fingerprinting and Large Experimental Data Set for
Visible Light Positioning", Sensors 21(9):3256, 2021) is a lobby with 11 ceiling luminaires
at z = 2.35 m (``luminaire_locations.csv``: ``Luminaire,x,y,z``) and a photodiode carried by
a robot over 7,344 points with HTC Vive ground truth (``Public_VLP_Dataset.csv``:
``index,L1..L11,x,y``). A reading of exactly :data:`NOT_DETECTED` means the LED was below the
receiver's floor. The files are read from a fetched copy (a directory holding them, or a
bare git directory and a commit); they are never part of this repository.

The receiver height is not in the files. :func:`estimate_receiver_height` reads it off the
survey: for each candidate height it fits every LED's Lambertian model (scale and order) to
the survey's log readings with the undetected readings censored at the floor, and keeps the
height of the highest profile likelihood. The shape of the fall-off with horizontal distance
(its curvature at the foot of an LED against its tail) is what separates the height from the
beam width.
"""

from __future__ import annotations

import csv
import io
import math
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.special import log_ndtr

from app.vlp.typing import FloatArray, IntArray

__all__ = [
    "DATA_FILE",
    "FIVE_LEDS",
    "LUMINAIRE_FILE",
    "MIN_DETECTED",
    "NOT_DETECTED",
    "MasseySurvey",
    "Split",
    "estimate_receiver_height",
    "facility_split",
    "load_survey",
    "multilateration",
    "shown_command",
    "weighted_knn",
]

DATA_FILE = "Public_VLP_Dataset.csv"
LUMINAIRE_FILE = "luminaire_locations.csv"
# The dataset's detector floor: a reading of exactly this value means "not detected".
NOT_DETECTED = 15.0
# Five of the lobby's eleven luminaires (1-based), as a five-LED room: of all choices of five,
# one under which the most survey points detect at least three (85 %); the others see too few
# LEDs for any fit. Test points that detect fewer than MIN_DETECTED of them are left out.
FIVE_LEDS = (4, 5, 7, 10, 11)
MIN_DETECTED = 3


@dataclass(frozen=True)
class MasseySurvey:
    """The survey: LED positions (M x 3), points (n x 2) and readings (n x M, NaN = not
    detected), in the dataset's room coordinates (metres)."""

    leds: FloatArray
    points: FloatArray
    readings: FloatArray
    floor: float = NOT_DETECTED

    @property
    def detected(self) -> np.ndarray:
        """(n, M) bool: the LED was detected at the point."""
        return np.isfinite(self.readings)

    def with_leds(self, indices: list[int]) -> MasseySurvey:
        """The same survey with only the LEDs ``indices`` (0-based): a sparser room."""
        return MasseySurvey(
            leds=self.leds[indices], points=self.points, readings=self.readings[:, indices]
        )


@dataclass(frozen=True)
class Split:
    """Indices of the survey points (calibration) and of the test points."""

    survey: IntArray
    test: IntArray


def _read_text(source: Path, name: str, commit: str | None) -> str:
    if (source / name).is_file():
        return (source / name).read_text(encoding="utf-8")
    if commit is None:
        raise FileNotFoundError(f"{source / name} not found (a git directory needs --commit)")
    return subprocess.run(
        ["git", f"--git-dir={source}", "show", f"{commit}:{name}"],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout


def shown_command(prog: str, given: Sequence[str], data: Path) -> str:
    """The command line a results page prints: ``prog`` and the arguments ``given``, with the
    fetched copy's path (the reader's own) shown as ``DATA``."""
    return " ".join([prog] + ["DATA" if arg == str(data) else arg for arg in given])


def load_survey(source: Path, commit: str | None = None) -> MasseySurvey:
    """Read the survey from ``source``: a directory holding :data:`DATA_FILE` and
    :data:`LUMINAIRE_FILE`, or a bare git directory read at ``commit``.

    Readings equal to :data:`NOT_DETECTED` become NaN.
    """
    leds_rows = list(csv.DictReader(io.StringIO(_read_text(source, LUMINAIRE_FILE, commit))))
    names = [row["Luminaire"] for row in leds_rows]
    leds = np.array([[float(row[c]) for c in ("x", "y", "z")] for row in leds_rows])
    rows = list(csv.DictReader(io.StringIO(_read_text(source, DATA_FILE, commit))))
    points = np.array([[float(row["x"]), float(row["y"])] for row in rows])
    readings = np.array([[float(row[name]) for name in names] for row in rows])
    readings[readings <= NOT_DETECTED] = np.nan
    return MasseySurvey(leds=leds, points=points, readings=readings)


def facility_split(
    points: FloatArray, *, cell_m: float = 1.0, seed: int = 0, max_test: int | None = None
) -> Split:
    """About one survey point per ``cell_m`` square: in each cell of a ``cell_m`` grid over
    the points' bounding box, the point nearest the cell's centre (when it lies within the
    cell). Every other point is a test point (``max_test`` of them drawn at random when set).
    """
    lo = points.min(axis=0)
    cells = np.floor((points - lo) / cell_m).astype(np.int64)
    centres = lo + (cells + 0.5) * cell_m
    distance = np.hypot(*(points - centres).T)
    chosen: dict[tuple[int, int], int] = {}
    for index in np.argsort(distance, kind="stable"):
        chosen.setdefault((int(cells[index, 0]), int(cells[index, 1])), int(index))
    survey = np.array(sorted(chosen.values()), dtype=np.int64)
    test = np.setdiff1d(np.arange(len(points)), survey)
    if max_test is not None and len(test) > max_test:
        test = np.sort(np.random.default_rng(seed).choice(test, max_test, replace=False))
    return Split(survey=survey, test=test)


def _profile_nll(
    log_readings: FloatArray, detected: np.ndarray, r2: FloatArray, dz: float, log_floor: float
) -> float:
    """Minus the censored log-likelihood at height drop ``dz``, maximised over each LED's
    log scale and Lambertian order and one log-noise sd."""
    m_leds = r2.shape[1]

    def nll(theta: FloatArray) -> float:
        scale, order, log_sd = theta[:m_leds], theta[m_leds:-1], theta[-1]
        sd = math.exp(log_sd)
        mean = scale + (order + 1) * math.log(dz) - (order + 3) / 2 * np.log(dz * dz + r2)
        seen = -0.5 * ((log_readings - mean) / sd) ** 2 - log_sd
        unseen = log_ndtr((log_floor - mean) / sd)
        return -float(np.where(detected, seen, unseen).sum())

    start = np.r_[np.full(m_leds, np.nanmedian(log_readings) + 1.0), np.ones(m_leds), -1.5]
    bounds = [(None, None)] * m_leds + [(0.0, 30.0)] * m_leds + [(-6.0, 2.0)]
    return float(minimize(nll, start, method="L-BFGS-B", bounds=bounds).fun)


def estimate_receiver_height(
    survey: MasseySurvey, indices: IntArray, candidates: FloatArray
) -> tuple[float, FloatArray]:
    """The receiver height (m above the floor) of highest profile likelihood among
    ``candidates``, from the survey points ``indices``; also each candidate's minus
    log-likelihood (same order), for the report."""
    points, readings = survey.points[indices], survey.readings[indices]
    detected = np.isfinite(readings)
    log_readings = np.log(np.where(detected, readings, survey.floor))
    r2 = ((points[:, None, :] - survey.leds[None, :, :2]) ** 2).sum(axis=-1)
    led_z = float(np.mean(survey.leds[:, 2]))
    nll = np.array(
        [
            _profile_nll(log_readings, detected, r2, led_z - z, math.log(survey.floor))
            for z in candidates
        ]
    )
    return float(candidates[int(np.argmin(nll))]), nll


def weighted_knn(
    reference_points: FloatArray,
    reference_readings: FloatArray,
    readings: FloatArray,
    *,
    k: int = 4,
    floor: float = NOT_DETECTED,
) -> FloatArray:
    """Weighted k-nearest-neighbour fingerprinting (what FIND3-style systems do).

    Readings (NaN = not detected, taken as ``floor``) are compared in log space; the
    estimate is the inverse-distance-weighted mean of the ``k`` nearest survey points.
    Shapes: reference (S, 2) and (S, M), readings (n, M) -> (n, 2).
    """
    ref = np.log(np.nan_to_num(reference_readings, nan=floor))
    obs = np.log(np.nan_to_num(readings, nan=floor))
    distance = np.sqrt(((obs[:, None, :] - ref[None, :, :]) ** 2).sum(axis=-1))
    nearest = np.argsort(distance, axis=1)[:, :k]
    weights = 1.0 / (np.take_along_axis(distance, nearest, axis=1) + 1e-9)
    weights /= weights.sum(axis=1, keepdims=True)
    found: FloatArray = np.einsum("nk,nkd->nd", weights, reference_points[nearest])
    return found


def multilateration(
    leds_xy: FloatArray,
    led_scale: FloatArray,
    lambertian_order: FloatArray,
    dz: float,
    readings: FloatArray,
    *,
    fallback: FloatArray,
) -> FloatArray:
    """Plain RSS multilateration by linear least squares.

    Each detected LED's reading ``a = c_i dz^(m_i+1) / d^(m_i+3)`` (Lambertian, level
    receiver) gives a distance ``d_i`` and a horizontal range ``r_i^2 = d_i^2 - dz^2``;
    subtracting the first circle from the others leaves a linear system in (x, y). Fewer
    than three detected LEDs: ``fallback``. Shapes: leds (M, 2), scales and orders (M,),
    readings (n, M) -> (n, 2).
    """
    out = np.empty((len(readings), 2))
    for row, amplitude in enumerate(readings):
        seen = np.flatnonzero(np.isfinite(amplitude) & (amplitude > 0))
        if len(seen) < 3:
            out[row] = fallback
            continue
        order = lambertian_order[seen]
        d = (led_scale[seen] * dz ** (order + 1) / amplitude[seen]) ** (1.0 / (order + 3))
        r2 = np.maximum(d * d - dz * dz, 0.0)
        xy = leds_xy[seen]
        a = 2.0 * (xy[1:] - xy[0])
        b = r2[0] - r2[1:] + (xy[1:] ** 2).sum(axis=1) - (xy[0] ** 2).sum()
        out[row] = np.linalg.lstsq(a, b, rcond=None)[0]
    return out
