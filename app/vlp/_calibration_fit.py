"""Least-squares kernels of the survey calibration (inputs already validated).

Split out of :mod:`app.vlp.calibration`, which holds the public functions and documents the
model; these functions trust their input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from .beams import BeamArrays, beam_arrays, evaluate_beams
from .channel import lambertian_order, led_constants
from .constants import DEFAULT_LED_NORMAL
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
    "MIN_ROWS_FOR_TILT",
    "SURFACE_NAMES",
    "LedFit",
    "LedRows",
    "classify",
    "diffuse_rows",
    "fit_jointly",
    "fit_led",
    "led_rows",
    "rms_per_led",
    "tilt_frame",
]

# Lambertian orders allowed in the fit: half-power angles between 89.5 and 0.5 degrees.
MIN_ORDER = float(lambertian_order(89.5))
MAX_ORDER = float(lambertian_order(0.5))
# In-view survey rows needed to fit the order as well as the amplitude ...
MIN_ROWS_FOR_ORDER = 3
# ... and the LED's x, y as well (4 parameters from fewer rows would fit the noise) ...
MIN_ROWS_FOR_POSITION = 8
# ... and the tilt of its normal too (6 parameters).
MIN_ROWS_FOR_TILT = 12
# Cost decrease (in noise variances) a fitted LED tilt must bring to be kept: 2 + 3 sqrt(2 * 2)
# for its two parameters (chi-squared with 2 degrees of freedom, 3 sd above its mean).
TILT_SIGNIFICANCE = 8.0
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
    """All survey rows of one LED and its model ``r (x0 h_los(p; m, s + shift, n) + d . rho)``.

    ``offsets`` are the points minus the LED's NOMINAL ``(x, y)``; ``diffuse`` the reflected
    amplitude per unit reflectance of each surface (nominal LED, ratio 1), shape (n, 3).
    The LED's normal is ``n(u, v)``: the layout's ``normal`` tilted by ``t = tan(bound)
    disc(u, v)`` along ``frame`` (two unit vectors across it), ``(u, v)`` in the unit square
    and ``disc`` the smooth map of the square onto the unit disc, so that any ``(u, v)`` is
    within ``bound`` of the layout's normal. Rows that are ``censored`` (not detected) say
    only that the amplitude is below ``floor``: their residual is the model's excess over
    the floor (0 below it), the least-squares form of the censored Gaussian likelihood.
    """

    offsets: FloatArray  # (n, 2), m
    dz: float  # LED height above the receivers' plane, m
    amplitudes: FloatArray  # (n,), 0 where censored
    base: float  # x_i^nominal A G_f G_c / (2 pi)
    cos_fov: float
    diffuse: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    normal: FloatArray = field(default_factory=lambda: np.array(DEFAULT_LED_NORMAL))
    frame: FloatArray = field(default_factory=lambda: np.eye(3)[:2].copy())
    tilt_scale: float = 0.0  # tan(bound); 0: the normal is the layout's
    censored: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    floor: float = 0.0
    # The LED's tabulated beam (its order is then 0 and not fitted): the line of sight is
    # multiplied by I(c), c = n . (r - s) / d.
    beam: BeamArrays | None = None

    @property
    def size(self) -> int:
        return int(self.amplitudes.size)

    @property
    def is_censored(self) -> BoolArray:
        if self.censored.size == 0:
            return np.zeros(self.size, dtype=bool)
        return self.censored

    def normal_at(self, tilt: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The unit normal (3,) at ``tilt = (u, v)`` and its derivatives (2, 3) along u, v."""
        u, v = float(tilt[0]), float(tilt[1])
        root_u, root_v = math.sqrt(1.0 - 0.5 * u * u), math.sqrt(1.0 - 0.5 * v * v)
        t = self.tilt_scale * np.array([u * root_v, v * root_u])
        # d t / d(u, v): rows t_x, t_y.
        dt = self.tilt_scale * np.array(
            [[root_v, -0.5 * u * v / root_v], [-0.5 * u * v / root_u, root_u]]
        )
        w = self.normal + t @ self.frame
        length = float(np.linalg.norm(w))
        unit = w / length
        # d unit / d t_j = (e_j - unit (unit . e_j)) / |w|
        along_t = (self.frame - np.outer(self.frame @ unit, unit)) / length  # (2, 3)
        return unit, dt.T @ along_t

    def geometry(
        self, shift: FloatArray, tilt: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray, FloatArray, FloatArray]:
        """``ln cos`` of the emission and incidence angles, ``d^2``, the mask of rows in the
        receiver's view and ahead of the LED, ``c = n . (r - s)`` and ``r - s`` (n, 3)."""
        rel = self.offsets - shift[None, :]
        to_rx = np.column_stack((rel, np.full(rel.shape[0], -self.dz)))
        unit = self.normal if tilt is None else self.normal_at(tilt)[0]
        facing = to_rx @ unit
        dist_sq = rel[:, 0] ** 2 + rel[:, 1] ** 2 + self.dz**2
        half_log_d2 = 0.5 * np.log(dist_sq)
        log_cos_phi = math.log(self.dz) - half_log_d2
        view = (np.exp(log_cos_phi) >= self.cos_fov - 1e-15) & (facing > 0)
        log_cos_alpha = np.log(np.where(facing > 0, facing, 1.0)) - half_log_d2
        return log_cos_alpha, log_cos_phi, dist_sq, view, facing, to_rx

    def line_of_sight(
        self, order: float, shift: FloatArray, tilt: FloatArray | None = None
    ) -> FloatArray:
        """``x0 h_los`` at ratio 1 (0 outside the FOV and behind the LED's face)."""
        return self._line_of_sight(order, shift, tilt)[0]

    def _line_of_sight(
        self, order: float, shift: FloatArray, tilt: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """:meth:`line_of_sight`, the Lambertian part alone (the whole without a beam) and
        ``dI/dc`` of the beam (zeros without one)."""
        log_alpha, log_phi, dist_sq, view, facing, _ = self.geometry(shift, tilt)
        gain = self.base * (order + 1.0) * np.exp(order * log_alpha + log_phi) / dist_sq
        lambertian = np.asarray(np.where(view, gain, 0.0))
        if self.beam is None:
            return lambertian, lambertian, np.zeros_like(lambertian)
        intensity, slope = evaluate_beams(self.beam, (facing / np.sqrt(dist_sq))[None, :])
        return lambertian * intensity[0], lambertian, slope[0]

    def reflected(self, rho: FloatArray) -> FloatArray:
        if self.diffuse.shape[0] == 0:
            return np.zeros(self.size)
        return np.asarray(self.diffuse @ rho)

    def model(
        self,
        ratio: float,
        order: float,
        shift: FloatArray,
        rho: FloatArray,
        tilt: FloatArray | None = None,
    ) -> FloatArray:
        return np.asarray(ratio * (self.line_of_sight(order, shift, tilt) + self.reflected(rho)))

    def residuals(self, fit: LedFit, rho: FloatArray) -> FloatArray:
        """Model minus measurement; for censored rows the model's excess over the floor."""
        modelled = self.model(fit.ratio, fit.order, fit.shift, rho, fit.tilt)
        censored = self.is_censored
        return np.asarray(
            np.where(censored, np.maximum(modelled - self.floor, 0.0), modelled - self.amplitudes)
        )

    def jacobian(
        self,
        ratio: float,
        order: float,
        shift: FloatArray,
        rho: FloatArray,
        tilt: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Columns d/d(ratio, order, shift_x, shift_y, u, v), shape (n, 6), and d/d rho, (n, 3)."""
        tilt = np.zeros(2) if tilt is None else tilt
        unit, along_uv = self.normal_at(tilt)
        log_alpha, _, dist_sq, view, facing, to_rx = self.geometry(shift, tilt)
        los, lambertian, beam_slope = self._line_of_sight(order, shift, tilt)
        safe = np.where(view, facing, 1.0)
        rel = to_rx[:, :2]
        d_shift = (
            ratio
            * los[:, None]
            * (((order + 3.0) / dist_sq)[:, None] * rel - order * unit[None, :2] / safe[:, None])
        )
        d_tilt = ratio * los[:, None] * order * (to_rx @ along_uv.T) / safe[:, None]
        if self.beam is not None:
            # I(c), c = n . (r - s) / d: the shift moves s (dc = -(n / d - c (r - s) / d^2)),
            # the tilt n (dc = (r - s) . dn / d).
            dist = np.sqrt(dist_sq)
            cosine = facing / dist
            along = ratio * lambertian * beam_slope / dist
            d_shift -= along[:, None] * (unit[None, :2] - (cosine / dist)[:, None] * rel)
            d_tilt += along[:, None] * (to_rx @ along_uv.T)
        columns = np.column_stack(
            (
                los + self.reflected(rho),
                ratio * los * (1.0 / (order + 1.0) + log_alpha),
                d_shift,
                d_tilt,
            )
        )
        d_rho = ratio * self.diffuse if self.diffuse.shape[0] else np.zeros((self.size, 3))
        return columns, d_rho

    def residual_jacobian(self, fit: LedFit, rho: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:meth:`jacobian` of :meth:`residuals` (censored rows below the floor: zero rows)."""
        columns, d_rho = self.jacobian(fit.ratio, fit.order, fit.shift, rho, fit.tilt)
        censored = self.is_censored
        if censored.any():
            modelled = self.model(fit.ratio, fit.order, fit.shift, rho, fit.tilt)
            quiet = censored & (modelled <= self.floor)
            columns = np.where(quiet[:, None], 0.0, columns)
            d_rho = np.where(quiet[:, None], 0.0, d_rho)
        return columns, d_rho

    def in_view(self) -> BoolArray:
        """Rows inside the field of view at the nominal position and normal."""
        return self.geometry(np.zeros(2))[3]

    def detected_in_view(self) -> int:
        """Rows in view whose LED was detected (those that carry a number)."""
        return int(np.count_nonzero(self.in_view() & ~self.is_censored))


@dataclass(frozen=True)
class LedFit:
    """One LED's fitted ``ratio = r_i``, order, shift of ``(x, y)``, tilt ``(u, v)`` of its
    normal (:class:`LedRows`) and which were free."""

    ratio: float
    order: float
    shift: FloatArray
    free: tuple[bool, bool, bool, bool, bool, bool]  # ratio, order, shift x, y, tilt u, v
    converged: bool = True
    tilt: FloatArray = field(default_factory=lambda: np.zeros(2))

    def _full(self) -> FloatArray:
        return np.array([self.ratio, self.order, *self.shift, *self.tilt], dtype=np.float64)

    def params(self) -> FloatArray:
        return np.asarray(self._full()[np.array(self.free)])

    def with_params(self, values: FloatArray, converged: bool = True) -> LedFit:
        full = self._full()
        full[np.array(self.free)] = values
        return LedFit(
            float(full[0]), float(full[1]), full[2:4].copy(), self.free, converged, full[4:].copy()
        )


def tilt_frame(normal: FloatArray) -> FloatArray:
    """Two unit vectors across ``normal`` (2, 3): for straight down, +x and +y."""
    e1 = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    e1 = e1 / np.linalg.norm(e1)
    return np.array([e1, np.cross(e1, normal)])


def led_rows(
    layout: Layout,
    index: int,
    points: FloatArray,
    amplitudes: FloatArray,
    diffuse: FloatArray | None = None,
    *,
    tilt_bound_deg: float = 0.0,
    floor: float = 0.0,
) -> LedRows:
    """The rows of LED ``index`` (``diffuse``: its per-surface reflected amplitudes, (n, 3));
    NaN amplitudes are censored below ``floor``."""
    led = layout.leds[index]
    orders, prefactors = led_constants(layout)
    beam = None if led.beam is None else beam_arrays([led.beam])
    base = float(layout.pilot_amplitudes[index] * prefactors[index] / (orders[index] + 1.0))
    normal = np.array(led.normal, dtype=np.float64)
    censored = np.isnan(amplitudes)
    return LedRows(
        offsets=points - np.array([led.x, led.y])[None, :],
        dz=led.z - layout.grid.receiver_height,
        amplitudes=np.where(censored, 0.0, amplitudes),
        base=base,
        cos_fov=math.cos(math.radians(layout.receiver.fov_deg)),
        diffuse=np.zeros((0, 3)) if diffuse is None else diffuse,
        normal=normal,
        frame=tilt_frame(normal),
        tilt_scale=math.tan(math.radians(tilt_bound_deg)),
        censored=censored,
        floor=floor,
        beam=beam,
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
    lower = np.array([0.0, MIN_ORDER, -shift_bound, -shift_bound, -1.0, -1.0])
    upper = np.array([np.inf, MAX_ORDER, shift_bound, shift_bound, 1.0, 1.0])
    return lower[np.array(fit.free)], upper[np.array(fit.free)]


def fit_led(rows: LedRows, nominal_order: float, rho: FloatArray, shift_bound: float) -> LedFit:
    """Least-squares ``(r_i, m_i, shift_i, tilt_i)`` of one LED with the reflectances ``rho``
    fixed.

    Counting only detected rows in view, ``m_i`` stays nominal with fewer than
    :data:`MIN_ROWS_FOR_ORDER` of them, the shift 0 with fewer than
    :data:`MIN_ROWS_FOR_POSITION` or ``shift_bound == 0``, the normal the layout's with fewer
    than :data:`MIN_ROWS_FOR_TILT` or a tilt bound of 0. A tilt and a shift move the beam
    alike near its foot, so the tilt is kept only when it lowers the cost by more than
    chance would (:data:`TILT_SIGNIFICANCE` noise variances, the noise taken from the fit
    without it): a level LED is not given the noise's tilt and the shift's spread with it.
    """
    n_view = rows.detected_in_view()
    free_shift = shift_bound > 0 and n_view >= MIN_ROWS_FOR_POSITION
    free_order = n_view >= MIN_ROWS_FOR_ORDER and rows.beam is None
    level = (True, free_order, free_shift, free_shift, False, False)
    fit, cost = _fit_led_with(
        rows, LedFit(1.0, nominal_order, np.zeros(2), level), rho, shift_bound
    )
    if not (rows.tilt_scale > 0 and n_view >= MIN_ROWS_FOR_TILT):
        return fit
    tilted_free = (*level[:4], True, True)
    tilted, tilted_cost = _fit_led_with(
        rows, replace(fit, free=tilted_free), rho, shift_bound, from_start=False
    )
    dof = max(n_view - int(np.count_nonzero(level)), 1)
    noise_var = 2.0 * cost / dof
    if noise_var > 0 and 2.0 * (cost - tilted_cost) > TILT_SIGNIFICANCE * noise_var:
        return tilted
    return fit


def _fit_led_with(
    rows: LedRows, start: LedFit, rho: FloatArray, shift_bound: float, *, from_start: bool = True
) -> tuple[LedFit, float]:
    """The bounded least squares of the free parameters of ``start`` and its cost (in the
    amplitudes' unit squared, halved); also from the log-linear start unless only
    ``from_start`` is False (then from ``start`` alone)."""
    scale = max(
        float(np.max(np.abs(rows.amplitudes))),
        float(np.max(rows.model(1.0, start.order, np.zeros(2), rho))),
    )
    mask = np.array(start.free)

    def residuals(params: FloatArray) -> FloatArray:
        return np.asarray(rows.residuals(start.with_params(params), rho) / scale)

    def jacobian(params: FloatArray) -> FloatArray:
        columns, _ = rows.residual_jacobian(start.with_params(params), rho)
        return np.asarray(columns[:, mask] / scale)

    lower, upper = _bounds(start, shift_bound)
    starts = [start.params()]
    log_start = log_linear_start(rows) if from_start and rows.beam is None else None
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
    return start.with_params(best.x, bool(best.status > 0)), float(best.cost) * scale**2


def log_linear_start(rows: LedRows) -> FloatArray | None:
    """Start ``(ratio, m)`` from ``ln a = ln(r base (m+1)) + m ln cos(alpha) + ln cos(phi) -
    ln d^2`` over the detected rows in view."""
    alpha_all, phi_all, dist_sq_all, view, _, _ = rows.geometry(np.zeros(2))
    view = view & ~rows.is_censored
    log_cos, dist_sq, meas = alpha_all[view], dist_sq_all[view], rows.amplitudes[view]
    log_phi = np.broadcast_to(phi_all, view.shape)[view]
    if meas.size == 0:
        return None
    positive = meas > 0.05 * float(np.max(meas)) if np.max(meas) > 0 else meas > 0
    if positive.sum() < 2 or np.ptp(log_cos[positive]) <= 1e-9:
        return None
    target = np.log(meas[positive]) + np.log(dist_sq[positive]) - log_phi[positive]
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
        parts = [r.residuals(f, current) for r, f in zip(rows, leds, strict=True)]
        return np.asarray(np.concatenate(parts) / scale)

    n_rows = sum(r.size for r in rows)
    dense = n_rows * (n_led_params + surfaces.size) <= _DENSE_JACOBIAN_LIMIT

    def jacobian(params: FloatArray) -> sp.csr_array | FloatArray:
        leds, current = unpack(params)
        blocks, shared = [], []
        for r, f in zip(rows, leds, strict=True):
            columns, d_rho = r.residual_jacobian(f, current)
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
    dof = max(sum(int(np.count_nonzero(~r.is_censored)) for r in rows) - sol.x.size, 1)
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
        columns, d_rho = r.residual_jacobian(f, rho)
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
