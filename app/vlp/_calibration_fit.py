"""Least-squares kernels of the survey calibration (inputs already validated).

Split out of :mod:`app.vlp.calibration`, which holds the public functions and documents the
model; these functions trust their input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from .channel import lambertian_order, led_constants
from .layout import Layout, Reflectance
from .reflections import diffuse_gains
from .typing import BoolArray, FloatArray, IntArray

if TYPE_CHECKING:
    from .survey import Survey

__all__ = [
    "MAX_ORDER",
    "MAX_REFLECTANCE",
    "MIN_ORDER",
    "MIN_ROWS_FOR_POSITION",
    "SURFACE_NAMES",
    "LedFit",
    "LedRows",
    "classify",
    "diffuse_rows",
    "fit_jointly",
    "fit_led",
    "led_rows",
    "rms_per_led",
]

# Lambertian orders allowed in the fit: half-power angles between 89.5 and 0.5 degrees.
MIN_ORDER = float(lambertian_order(89.5))
MAX_ORDER = float(lambertian_order(0.5))
# In-view survey rows needed to fit the order as well as the amplitude ...
MIN_ROWS_FOR_ORDER = 3
# ... and the LED's x, y as well (4 parameters from fewer rows would fit the noise).
MIN_ROWS_FOR_POSITION = 8
# Fitted reflectances stay in [0, MAX_REFLECTANCE] (a Reflectance must be below 1).
MAX_REFLECTANCE = 0.99
SURFACE_NAMES = ("walls", "floor", "ceiling")
# A surface whose reflected signal at the survey rows is below this fraction of the
# strongest line-of-sight amplitude cannot be told from zero (e.g. the floor for receivers
# facing up with a FOV below 90 degrees): it is not fitted.
_IDENTIFIABLE_FRACTION = 1e-6
# Joint fits whose Jacobian has at most this many entries use it dense (exact trust-region
# steps); larger ones keep it sparse (LSMR steps).
_DENSE_JACOBIAN_LIMIT = 4_000_000
# Unit reflectance is not a valid Reflectance; the first bounce is linear in it, so the
# gains are computed at this value and divided by it.
_PROBE_REFLECTANCE = 0.5


@dataclass(frozen=True)
class LedRows:
    """All survey rows of one LED and its model ``r (x0 h_los(p; m, s + shift) + d . rho)``.

    ``offsets`` are the points minus the LED's NOMINAL ``(x, y)``; ``diffuse`` the reflected
    amplitude per unit reflectance of each surface (nominal LED, ratio 1), shape (n, 3).
    """

    offsets: FloatArray  # (n, 2), m
    dz: float  # LED height above the receivers' plane, m
    amplitudes: FloatArray  # (n,)
    base: float  # x_i^nominal A G_f G_c / (2 pi)
    cos_fov: float
    diffuse: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def size(self) -> int:
        return int(self.amplitudes.size)

    def geometry(self, shift: FloatArray) -> tuple[FloatArray, FloatArray, BoolArray]:
        """``ln cos`` of the incidence angle, ``d^2`` and the field-of-view mask."""
        rel = self.offsets - shift[None, :]
        dist_sq = rel[:, 0] ** 2 + rel[:, 1] ** 2 + self.dz**2
        log_cos = math.log(self.dz) - 0.5 * np.log(dist_sq)
        view = np.exp(log_cos) >= self.cos_fov - 1e-15
        return log_cos, dist_sq, view

    def line_of_sight(self, order: float, shift: FloatArray) -> FloatArray:
        """``x0 h_los`` at ratio 1 (0 outside the FOV)."""
        log_cos, dist_sq, view = self.geometry(shift)
        gain = self.base * (order + 1.0) * np.exp((order + 1.0) * log_cos) / dist_sq
        return np.asarray(np.where(view, gain, 0.0))

    def reflected(self, rho: FloatArray) -> FloatArray:
        if self.diffuse.shape[0] == 0:
            return np.zeros(self.size)
        return np.asarray(self.diffuse @ rho)

    def model(self, ratio: float, order: float, shift: FloatArray, rho: FloatArray) -> FloatArray:
        return np.asarray(ratio * (self.line_of_sight(order, shift) + self.reflected(rho)))

    def jacobian(
        self, ratio: float, order: float, shift: FloatArray, rho: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Columns d/d(ratio, order, shift_x, shift_y), shape (n, 4), and d/d rho, (n, 3)."""
        log_cos, dist_sq, _ = self.geometry(shift)
        los = self.line_of_sight(order, shift)
        rel = self.offsets - shift[None, :]
        d_shift = ((order + 3.0) * ratio * los / dist_sq)[:, None] * rel
        columns = np.column_stack(
            (
                los + self.reflected(rho),
                ratio * los * (1.0 / (order + 1.0) + log_cos),
                d_shift,
            )
        )
        d_rho = ratio * self.diffuse if self.diffuse.shape[0] else np.zeros((self.size, 3))
        return columns, d_rho

    def in_view(self) -> BoolArray:
        """Rows inside the field of view at the nominal position."""
        return self.geometry(np.zeros(2))[2]


@dataclass(frozen=True)
class LedFit:
    """One LED's fitted ``ratio = r_i``, order, shift of ``(x, y)`` and which were free."""

    ratio: float
    order: float
    shift: FloatArray
    free: tuple[bool, bool, bool, bool]  # ratio, order, shift x, shift y
    converged: bool = True

    def params(self) -> FloatArray:
        full = np.array([self.ratio, self.order, self.shift[0], self.shift[1]])
        return np.asarray(full[np.array(self.free)])

    def with_params(self, values: FloatArray, converged: bool = True) -> LedFit:
        full = np.array([self.ratio, self.order, self.shift[0], self.shift[1]])
        full[np.array(self.free)] = values
        return LedFit(float(full[0]), float(full[1]), full[2:].copy(), self.free, converged)


def led_rows(
    layout: Layout,
    index: int,
    points: FloatArray,
    amplitudes: FloatArray,
    diffuse: FloatArray | None = None,
) -> LedRows:
    """The rows of LED ``index`` (``diffuse``: its per-surface reflected amplitudes, (n, 3))."""
    led = layout.leds[index]
    orders, prefactors = led_constants(layout)
    base = float(layout.pilot_amplitudes[index] * prefactors[index] / (orders[index] + 1.0))
    return LedRows(
        offsets=points - np.array([led.x, led.y])[None, :],
        dz=led.z - layout.grid.receiver_height,
        amplitudes=amplitudes,
        base=base,
        cos_fov=math.cos(math.radians(layout.receiver.fov_deg)),
        diffuse=np.zeros((0, 3)) if diffuse is None else diffuse,
    )


def diffuse_rows(layout: Layout, survey: Survey) -> FloatArray:
    """Reflected amplitude per unit reflectance of each surface, per survey row, (S, 3).

    First bounce off the nominal LEDs (:func:`app.vlp.reflections.diffuse_gains`) at the
    receivers' height, times each row's LED's nominal pilot amplitude.
    """
    unique, inverse = np.unique(survey.points, axis=0, return_inverse=True)
    xyz = np.column_stack((unique, np.full(unique.shape[0], layout.grid.receiver_height)))
    out = np.zeros((survey.n_rows, len(SURFACE_NAMES)))
    pilots = layout.pilot_amplitudes
    for s, name in enumerate(SURFACE_NAMES):
        probe = Reflectance(
            **{n: (_PROBE_REFLECTANCE if n == name else 0.0) for n in SURFACE_NAMES}
        )
        gains = diffuse_gains(layout, xyz, reflectance=probe) / _PROBE_REFLECTANCE  # (M, U)
        out[:, s] = gains[survey.led_indices, inverse.ravel()] * pilots[survey.led_indices]
    return out


def identifiable_surfaces(rows: list[LedRows]) -> BoolArray:
    """Surfaces whose reflected signal at the survey rows can be told from zero."""
    strongest = max(float(np.max(r.line_of_sight(1.0, np.zeros(2)), initial=0.0)) for r in rows)
    reach = np.zeros(len(SURFACE_NAMES))
    for r in rows:
        if r.diffuse.shape[0]:
            reach = np.maximum(reach, np.max(np.abs(r.diffuse), axis=0, initial=0.0))
    return np.asarray(reach > _IDENTIFIABLE_FRACTION * max(strongest, 1e-300))


def _bounds(fit: LedFit, shift_bound: float) -> tuple[FloatArray, FloatArray]:
    lower = np.array([0.0, MIN_ORDER, -shift_bound, -shift_bound])[np.array(fit.free)]
    upper = np.array([np.inf, MAX_ORDER, shift_bound, shift_bound])[np.array(fit.free)]
    return lower, upper


def fit_led(rows: LedRows, nominal_order: float, rho: FloatArray, shift_bound: float) -> LedFit:
    """Least-squares ``(r_i, m_i, shift_i)`` of one LED with the reflectances ``rho`` fixed.

    ``m_i`` stays nominal with fewer than :data:`MIN_ROWS_FOR_ORDER` rows in view, the shift
    0 with fewer than :data:`MIN_ROWS_FOR_POSITION` or ``shift_bound == 0``.
    """
    n_view = int(np.count_nonzero(rows.in_view()))
    free_shift = shift_bound > 0 and n_view >= MIN_ROWS_FOR_POSITION
    free = (True, n_view >= MIN_ROWS_FOR_ORDER, free_shift, free_shift)
    start = LedFit(1.0, nominal_order, np.zeros(2), free)
    scale = max(
        float(np.max(np.abs(rows.amplitudes))),
        float(np.max(rows.model(1.0, nominal_order, np.zeros(2), rho))),
    )
    mask = np.array(free)

    def residuals(params: FloatArray) -> FloatArray:
        f = start.with_params(params)
        return np.asarray((rows.model(f.ratio, f.order, f.shift, rho) - rows.amplitudes) / scale)

    def jacobian(params: FloatArray) -> FloatArray:
        f = start.with_params(params)
        columns, _ = rows.jacobian(f.ratio, f.order, f.shift, rho)
        return np.asarray(columns[:, mask] / scale)

    lower, upper = _bounds(start, shift_bound)
    starts = [start.params()]
    log_start = log_linear_start(rows)
    if log_start is not None:
        starts.append(
            LedFit(float(log_start[0]), float(log_start[1]), np.zeros(2), start.free).params()
        )
    best = None
    for x0 in starts:
        sol = least_squares(
            residuals,
            np.clip(x0, lower + 1e-12, upper - 1e-12),
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
    return start.with_params(best.x, bool(best.status > 0))


def log_linear_start(rows: LedRows) -> FloatArray | None:
    """Start ``(ratio, m)`` from ``ln a = ln(r base (m+1)) + (m+1) ln cos - ln d^2``."""
    log_cos_all, dist_sq_all, view = rows.geometry(np.zeros(2))
    log_cos, dist_sq, meas = log_cos_all[view], dist_sq_all[view], rows.amplitudes[view]
    if meas.size == 0:
        return None
    positive = meas > 0.05 * float(np.max(meas)) if np.max(meas) > 0 else meas > 0
    if positive.sum() < 2 or np.ptp(log_cos[positive]) <= 1e-9:
        return None
    target = np.log(meas[positive]) + np.log(dist_sq[positive]) - log_cos[positive]
    design = np.column_stack((np.ones(int(positive.sum())), log_cos[positive]))
    weights = meas[positive] / np.max(meas[positive])  # var(ln a) ~ sigma^2 / a^2
    coef, *_ = np.linalg.lstsq(design * weights[:, None], target * weights, rcond=None)
    order = float(np.clip(coef[1], MIN_ORDER, MAX_ORDER))
    return np.array([math.exp(float(coef[0])) / (rows.base * (order + 1.0)), order])


@dataclass(frozen=True)
class JointFit:
    """Every LED's fit and the fitted reflectances with their standard deviations."""

    leds: list[LedFit]
    rho: FloatArray
    rho_sd: FloatArray  # NaN for surfaces not fitted
    converged: bool


def fit_jointly(
    rows: list[LedRows],
    fits: list[LedFit],
    rho: FloatArray,
    fitted_surfaces: BoolArray,
    shift_bound: float,
) -> JointFit:
    """All LEDs and the reflectances of ``fitted_surfaces`` together (one least squares).

    Every row depends on its LED's parameters and on the shared reflectances, so the
    Jacobian is block-diagonal plus a few dense columns; it is kept sparse. The standard
    deviations of the reflectances come from the Schur complement of the Fisher information
    (noise from the residuals), i.e. with every LED parameter free.
    """
    surfaces = np.flatnonzero(fitted_surfaces)
    sizes = [int(np.count_nonzero(f.free)) for f in fits]
    starts = np.cumsum([0, *sizes])
    n_led_params = int(starts[-1])
    scale = max(float(np.max(np.abs(r.amplitudes), initial=0.0)) for r in rows) or 1.0

    def unpack(params: FloatArray) -> tuple[list[LedFit], FloatArray]:
        current = rho.copy()
        current[surfaces] = params[n_led_params:]
        leds = [f.with_params(params[starts[i] : starts[i + 1]]) for i, f in enumerate(fits)]
        return leds, current

    def residuals(params: FloatArray) -> FloatArray:
        leds, current = unpack(params)
        parts = [
            r.model(f.ratio, f.order, f.shift, current) - r.amplitudes
            for r, f in zip(rows, leds, strict=True)
        ]
        return np.asarray(np.concatenate(parts) / scale)

    n_rows = sum(r.size for r in rows)
    dense = n_rows * (n_led_params + surfaces.size) <= _DENSE_JACOBIAN_LIMIT

    def jacobian(params: FloatArray) -> sp.csr_array | FloatArray:
        leds, current = unpack(params)
        blocks, shared = [], []
        for r, f in zip(rows, leds, strict=True):
            columns, d_rho = r.jacobian(f.ratio, f.order, f.shift, current)
            blocks.append(columns[:, np.array(f.free)])
            shared.append(d_rho[:, surfaces])
        led_part = sp.block_diag(blocks, format="csr")
        full = sp.csr_array(sp.hstack((led_part, sp.csr_array(np.vstack(shared)))) / scale)
        return full.toarray() if dense else full

    x0 = np.concatenate([f.params() for f in fits] + [rho[surfaces]])
    lower = np.concatenate([_bounds(f, shift_bound)[0] for f in fits] + [np.zeros(surfaces.size)])
    upper = np.concatenate(
        [_bounds(f, shift_bound)[1] for f in fits] + [np.full(surfaces.size, MAX_REFLECTANCE)]
    )
    sol = least_squares(
        residuals,
        np.clip(x0, lower + 1e-12, upper - 1e-12),
        jac=jacobian,
        bounds=(lower, upper),
        method="trf",
        x_scale="jac",
        tr_solver="exact" if dense else "lsmr",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=200,
    )
    leds, fitted = unpack(sol.x)
    dof = max(sum(r.size for r in rows) - sol.x.size, 1)
    noise_var = float(2.0 * sol.cost) * scale**2 / dof
    sd = np.full(len(SURFACE_NAMES), np.nan)
    sd[surfaces] = _shared_sd(rows, leds, fitted, surfaces, noise_var)
    return JointFit(leds, fitted, sd, bool(sol.status > 0))


def _shared_sd(
    rows: list[LedRows],
    leds: list[LedFit],
    rho: FloatArray,
    surfaces: IntArray,
    noise_var: float,
) -> FloatArray:
    """sd of the shared parameters: ``sigma^2 (C - sum_i B_i^T A_i^+ B_i)^-1``."""
    schur = np.zeros((surfaces.size, surfaces.size))
    for r, f in zip(rows, leds, strict=True):
        columns, d_rho = r.jacobian(f.ratio, f.order, f.shift, rho)
        own, shared = columns[:, np.array(f.free)], d_rho[:, surfaces]
        cross = own.T @ shared
        schur += shared.T @ shared - cross.T @ np.linalg.pinv(own.T @ own) @ cross
    try:
        cov = noise_var * np.linalg.inv(schur)
    except np.linalg.LinAlgError:
        return np.full(surfaces.size, np.inf)
    return np.asarray(np.sqrt(np.clip(np.diag(cov), 0.0, None)))


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
