"""Least-squares kernels of the survey calibration (inputs already validated).

Split out of :mod:`app.vlp.calibration`, which holds the public functions and documents the
model; these helpers trust their input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from ._typing import BoolArray, FloatArray
from .channel import lambertian_order, led_constants
from .layout import Layout

if TYPE_CHECKING:
    from .calibration import Survey

__all__ = [
    "MAX_ORDER",
    "MIN_ORDER",
    "LedRows",
    "classify",
    "fit_led",
    "led_rows",
    "model_amplitudes",
    "rms_per_led",
]

# Lambertian orders allowed in the fit: half-power angles between 89.5 and 0.5 degrees.
MIN_ORDER = float(lambertian_order(89.5))
MAX_ORDER = float(lambertian_order(0.5))
# In-view survey rows needed to fit the order as well as the amplitude.
MIN_ROWS_FOR_ORDER = 3


@dataclass(frozen=True)
class LedRows:
    """One LED's survey rows inside its field of view, and its model ``r x0 h(p; m)``."""

    log_cos: FloatArray  # ln(dz / d), the cosine of the incidence (= irradiance) angle
    dist_sq: FloatArray  # d^2, m^2
    amplitudes: FloatArray
    base: float  # x_i^nominal A G_f G_c / (2 pi)

    def model(self, ratio: float, order: float) -> FloatArray:
        return np.asarray(
            ratio * self.base * (order + 1.0) * np.exp((order + 1.0) * self.log_cos) / self.dist_sq
        )


def led_rows(
    layout: Layout, index: int, points: FloatArray, amplitudes: FloatArray
) -> tuple[LedRows, BoolArray]:
    led = layout.leds[index]
    dz = led.z - layout.grid.receiver_height
    dist_sq = (points[:, 0] - led.x) ** 2 + (points[:, 1] - led.y) ** 2 + dz**2
    cos_inc = dz / np.sqrt(dist_sq)
    view = cos_inc >= math.cos(math.radians(layout.receiver.fov_deg)) - 1e-15
    orders, prefactors = led_constants(layout)
    base = float(layout.pilot_amplitudes[index] * prefactors[index] / (orders[index] + 1.0))
    return LedRows(np.log(cos_inc[view]), dist_sq[view], amplitudes[view], base), view


def model_amplitudes(
    layout: Layout, survey: Survey, ratios: FloatArray, orders: FloatArray
) -> FloatArray:
    """``r_i x_i^nominal h(p_k; m_i)`` per survey row; 0 outside the field of view."""
    out = np.zeros(survey.n_rows)
    for i in range(layout.n_leds):
        rows = np.flatnonzero(survey.led_indices == i)
        selected, view = led_rows(layout, i, survey.points[rows], survey.amplitudes[rows])
        out[rows[view]] = selected.model(float(ratios[i]), float(orders[i]))
    return out


def fit_led(rows: LedRows, nominal_order: float) -> tuple[float, float, bool]:
    """Least-squares ``(r_i, m_i)`` of one LED (``m_i`` nominal when too few rows)."""
    scale = max(
        float(np.max(np.abs(rows.amplitudes))), float(np.max(rows.model(1.0, nominal_order)))
    )
    fit_order = rows.amplitudes.size >= MIN_ROWS_FOR_ORDER

    def unpack(params: FloatArray) -> tuple[float, float]:
        return float(params[0]), float(params[1]) if fit_order else nominal_order

    def residuals(params: FloatArray) -> FloatArray:
        return np.asarray((rows.model(*unpack(params)) - rows.amplitudes) / scale)

    def jacobian(params: FloatArray) -> FloatArray:
        ratio, order = unpack(params)
        model = rows.model(1.0, order) / scale
        d_order = ratio * model * (1.0 / (order + 1.0) + rows.log_cos)
        return np.column_stack((model, d_order) if fit_order else (model,))

    lower = np.array([0.0, MIN_ORDER])[: 2 if fit_order else 1]
    upper = np.array([np.inf, MAX_ORDER])[: lower.size]
    starts = [np.array([1.0, nominal_order]), log_linear_start(rows)]
    best = None
    for start in (s for s in starts if s is not None):
        x0 = np.clip(start[: lower.size], lower + 1e-12, upper - 1e-12)
        sol = least_squares(
            residuals,
            x0,
            jac=jacobian,
            bounds=(lower, upper),
            method="trf",
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            max_nfev=500,
        )
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None
    ratio, order = unpack(best.x)
    return ratio, order, bool(best.status > 0)


def log_linear_start(rows: LedRows) -> FloatArray | None:
    """Start ``(ratio, m)`` from ``ln a = ln(r base (m+1)) + (m+1) ln cos - ln d^2``."""
    log_cos, dist_sq, meas, base = rows.log_cos, rows.dist_sq, rows.amplitudes, rows.base
    positive = meas > 0.05 * float(np.max(meas)) if np.max(meas) > 0 else meas > 0
    if positive.sum() < 2 or np.ptp(log_cos[positive]) <= 1e-9:
        return None
    target = np.log(meas[positive]) + np.log(dist_sq[positive]) - log_cos[positive]
    design = np.column_stack((np.ones(int(positive.sum())), log_cos[positive]))
    weights = meas[positive] / np.max(meas[positive])  # var(ln a) ~ sigma^2 / a^2
    coef, *_ = np.linalg.lstsq(design * weights[:, None], target * weights, rcond=None)
    order = float(np.clip(coef[1], MIN_ORDER, MAX_ORDER))
    return np.array([math.exp(float(coef[0])) / (base * (order + 1.0)), order])


def classify(
    ratios: FloatArray,
    surveyed: BoolArray,
    detected: BoolArray,
    dimmed_below: float,
    dead_below: float,
) -> tuple[float, FloatArray, BoolArray, BoolArray]:
    """Common gain, relative amplitudes and the dead and dimmed masks."""
    gain = common_gain(ratios[surveyed & detected], dimmed_below)
    relative = np.where(surveyed, ratios / gain, 1.0)
    dead = surveyed & (~detected | (relative < dead_below))
    dimmed = surveyed & ~dead & (relative < dimmed_below)
    return gain, relative, dead, dimmed


def common_gain(ratios: FloatArray, dimmed_below: float) -> float:
    """Geometric mean of the per-LED ratios that are not far below their median."""
    if ratios.size == 0 or np.median(ratios) <= 0:
        return 1.0
    healthy = ratios[(ratios > 0) & (ratios >= dimmed_below * float(np.median(ratios)))]
    return float(np.exp(np.mean(np.log(healthy))))


def rms_per_led(survey: Survey, residuals: FloatArray, n_leds: int) -> FloatArray:
    counts = np.bincount(survey.led_indices, minlength=n_leds)
    sums = np.bincount(survey.led_indices, weights=residuals**2, minlength=n_leds)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan))
