"""What a survey tells of each LED's gain beyond its model: a smooth map of log factors.

A calibrated LED model (amplitude, beam, tilt, position) still misses what varies over the
floor in ways its parameters do not follow: a beam that a sparse survey pins only roughly, a
luminaire's diffuser, the light off a nearby wall, a shade. A survey sees it as log residuals
``y = log(a / f)`` that are correlated over the floor. Each LED ``j`` gets a Gaussian-process
interpolant of its rows' residuals (squared-exponential covariance of length scale ``l``,
signal variance ``s_j^2``, and a noise variance ``lambda s_j^2`` for what does not repeat
between neighbours); its posterior mean is::

    g_j(p) = sum_k w_kj exp(-|p - x_k|^2 / (2 l^2)),   w_.j = (R + lambda I)^-1 y_j

with ``R_kl = exp(-|x_k - x_l|^2 / (2 l^2))`` over the LED's rows (``s_j^2`` cancels)

and the room's model gain of LED ``j`` at ``p`` is multiplied by ``exp(g_j(p))``. Away from the
survey the map returns to 1 (the calibrated model). ``l`` and ``lambda`` are chosen among
candidates by the marginal likelihood of all LEDs' rows together (each LED's ``s_j^2`` at its
maximum; Rasmussen and Williams 2006, section 5.4.1). No map is kept unless that likelihood
beats the model alone (the rows independent, of their mean square) by :data:`MIN_EVIDENCE`,
the map's two parameters (Akaike's criterion: the map is expected to predict unsurveyed
points better): a survey that cannot show a map leaves the model as it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import GeometryError
from .typing import FloatArray

__all__ = [
    "LENGTH_SCALES_M",
    "MAX_ROWS_PER_LED",
    "MIN_EVIDENCE",
    "MIN_ROWS_PER_LED",
    "NOISE_RATIOS",
    "GainMap",
    "GainMapFit",
    "fit_gain_map",
]

# Candidate length scales (metres) and noise-to-signal variance ratios of the interpolant.
LENGTH_SCALES_M = (0.3, 0.5, 0.8, 1.2, 2.0)
NOISE_RATIOS = (0.03, 0.1, 0.3, 1.0, 3.0)
# An LED with fewer usable rows gets no map (its weights are 0).
MIN_ROWS_PER_LED = 6
# An LED's map rests on at most this many of its rows (evenly spread over the survey's order):
# the fit is cubic in them, and a denser survey adds little to a smooth map.
MAX_ROWS_PER_LED = 200
# Points evaluated at once (bounds the kernel's memory).
_CHUNK = 4096
_TINY_VARIANCE = 1e-24
# Log-likelihood ratio a map must reach over the model alone: its two parameters (Akaike).
MIN_EVIDENCE = 2.0


@dataclass(frozen=True)
class GainMap:
    """Per-LED log gain factors over the floor, as the survey's interpolant.

    Attributes
    ----------
    points : tuple of (x, y)
        The survey points the map rests on, metres (S of them).
    weights : tuple of tuples
        ``weights[k][j]``: point ``k``'s weight for LED ``j`` (S x M; 0 where the LED's row
        was not used).
    length_scale_m : float
        ``l``, metres.

    Raises
    ------
    GeometryError
        On ragged or non-finite weights, no point, or a length scale that is not positive;
        ``field`` names the input relative to ``gain_map``.
    """

    points: tuple[tuple[float, float], ...]
    weights: tuple[tuple[float, ...], ...]
    length_scale_m: float

    def __post_init__(self) -> None:
        if not self.points:
            raise GeometryError("a gain map needs at least one point", field="gain_map.points")
        if len(self.weights) != len(self.points):
            raise GeometryError(
                f"a gain map needs one row of weights per point: {len(self.points)} points, "
                f"{len(self.weights)} rows",
                field="gain_map.weights",
            )
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or not np.all(np.isfinite(points)):
            raise GeometryError(
                "gain_map.points must be finite (x, y) pairs", field="gain_map.points"
            )
        widths = {len(row) for row in self.weights}
        if len(widths) != 1 or not np.all(np.isfinite(np.asarray(self.weights, dtype=float))):
            raise GeometryError(
                "gain_map.weights must be rows of equal length of finite numbers",
                field="gain_map.weights",
            )
        scale = self.length_scale_m
        if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
            raise GeometryError(
                f"gain_map.length_scale_m must be a positive number, got {scale!r}",
                field="gain_map.length_scale_m",
            )

    @property
    def n_leds(self) -> int:
        """M: the LEDs the weights are for."""
        return len(self.weights[0])

    @property
    def mapped_leds(self) -> tuple[int, ...]:
        """The LEDs whose map is not 1 everywhere (some weight not 0)."""
        weights = np.asarray(self.weights)
        return tuple(int(j) for j in np.flatnonzero(np.any(weights != 0.0, axis=0)))

    def log_factors(self, points: FloatArray, led: int | None = None) -> FloatArray:
        """``g_j(p)`` at ``points``, of every LED or of one.

        Parameters
        ----------
        points : ndarray of shape (P, 2)
            Floor positions, metres.
        led : int, default=None
            Only this LED's.

        Returns
        -------
        log_factors : ndarray of shape (M, P), or (1, P) for one LED
        """
        where = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        nodes = np.asarray(self.points, dtype=np.float64)
        weights = np.asarray(self.weights, dtype=np.float64)
        leds = range(self.n_leds) if led is None else (led,)
        out = np.zeros((len(leds), where.shape[0]))
        for row, j in enumerate(leds):
            used = np.flatnonzero(weights[:, j])
            for first in range(0, where.shape[0], _CHUNK):
                chunk = where[first : first + _CHUNK]
                kernel = _kernel(chunk, nodes[used], self.length_scale_m)
                out[row, first : first + _CHUNK] = kernel @ weights[used, j]
        return out

    def without_leds(self, dropped: set[int]) -> GainMap:
        """The map of the LEDs not in ``dropped`` (their order kept)."""
        kept = [j for j in range(self.n_leds) if j not in dropped]
        return GainMap(
            self.points,
            tuple(tuple(row[j] for j in kept) for row in self.weights),
            self.length_scale_m,
        )

    def to_mapping(self) -> dict[str, object]:
        return {
            "points": [list(p) for p in self.points],
            "weights": [list(w) for w in self.weights],
            "length_scale_m": self.length_scale_m,
        }


@dataclass(frozen=True)
class GainMapFit:
    """A fitted map and what it did to the survey's rows.

    Attributes
    ----------
    gain_map : GainMap or None
        None when the survey does not show one (see the module).
    held_out : ndarray of shape (S,)
        Each row's log factor predicted without that row (the map's value for rows it did
        not use; 0 without a map): the honest residual of a row is ``y - held_out``.
    evidence : float
        The best candidate's log marginal likelihood over the model alone's (nats; the map is
        kept from :data:`MIN_EVIDENCE`).
    noise_ratio : float
        The best candidate's ``lambda`` (NaN without rows to fit).
    """

    gain_map: GainMap | None
    held_out: FloatArray
    evidence: float
    noise_ratio: float


def _held_out(kernel: FloatArray, y: FloatArray, ratio: float) -> tuple[FloatArray, FloatArray]:
    """Each row's mean predicted from the others, and the weights ``(R + lambda I)^-1 y``."""
    inverse = np.linalg.inv(kernel + ratio * np.eye(y.size))
    alpha = inverse @ y
    return y - alpha / np.diag(inverse), alpha


def _log_evidence(kernel: FloatArray, y: FloatArray, ratio: float) -> float:
    """Log marginal likelihood of ``y`` with the signal variance at its maximum."""
    cov = kernel + ratio * np.eye(y.size)
    factor = np.linalg.cholesky(cov)
    white = np.linalg.solve(factor, y)
    signal = float(white @ white) / y.size
    log_det = 2.0 * float(np.sum(np.log(np.diag(factor))))
    return -0.5 * (y.size * (math.log(2 * math.pi * signal) + 1.0) + log_det)


def _null_evidence(y: FloatArray) -> float:
    """The model alone: the rows independent, ``N(0, v)`` with ``v`` their mean square."""
    return -0.5 * y.size * (math.log(2 * math.pi * float(np.mean(y**2))) + 1.0)


def fit_gain_map(
    points: FloatArray, led_indices: np.ndarray, log_residuals: FloatArray, n_leds: int
) -> GainMapFit:
    """Fit every LED's map to its rows' log residuals.

    Parameters
    ----------
    points : ndarray of shape (S, 2)
        Each row's survey point, metres.
    led_indices : ndarray of shape (S,)
        Each row's LED.
    log_residuals : ndarray of shape (S,)
        ``log(a / f)``; NaN where a row is not to be used (not detected, not modelled).
    n_leds : int
        M.

    Returns
    -------
    GainMapFit
    """
    points = np.asarray(points, dtype=np.float64)
    leds = np.asarray(led_indices)
    y_all = np.asarray(log_residuals, dtype=np.float64)
    usable = np.isfinite(y_all)
    groups = [
        g
        for g in (
            _spread(np.flatnonzero(usable & (leds == j)))
            for j in range(n_leds)
            if np.count_nonzero(usable & (leds == j)) >= MIN_ROWS_PER_LED
        )
        # Residuals that are all but zero (a model exact to round-off) have nothing to map.
        if float(np.mean(y_all[g] ** 2)) > _TINY_VARIANCE
    ]
    held_out = np.zeros(y_all.size)
    if not groups:
        return GainMapFit(None, held_out, 0.0, math.nan)
    null = sum(_null_evidence(y_all[g]) for g in groups)
    best: tuple[float, float, float] | None = None
    for scale in LENGTH_SCALES_M:
        kernels = [_kernel(points[g], points[g], scale) for g in groups]
        for ratio in NOISE_RATIOS:
            total = sum(
                _log_evidence(k, y_all[g], ratio) for k, g in zip(kernels, groups, strict=True)
            )
            if best is None or total > best[0]:
                best = (total, scale, ratio)
    assert best is not None  # LENGTH_SCALES_M and NOISE_RATIOS are not empty
    total, scale, ratio = best
    evidence = total - null
    if evidence < MIN_EVIDENCE:
        return GainMapFit(None, held_out, evidence, ratio)
    # The map's own points: every fitted row's point, once.
    fitted = np.concatenate(groups)
    nodes, node_of_row = np.unique(points[fitted], axis=0, return_inverse=True)
    node_of = dict(zip(fitted.tolist(), node_of_row.ravel().tolist(), strict=True))
    weights = np.zeros((nodes.shape[0], n_leds))
    for g in groups:
        loo_mean, alpha = _held_out(_kernel(points[g], points[g], scale), y_all[g], ratio)
        held_out[g] = loo_mean
        np.add.at(weights[:, int(leds[g[0]])], [node_of[i] for i in g.tolist()], alpha)
    gain_map = GainMap(
        tuple((float(x), float(y)) for x, y in nodes),
        tuple(tuple(float(v) for v in row) for row in weights),
        float(scale),
    )
    rest = np.ones(y_all.size, dtype=bool)
    rest[fitted] = False
    for j in range(n_leds):
        of_led = np.flatnonzero(rest & (leds == j))
        if of_led.size:
            held_out[of_led] = gain_map.log_factors(points[of_led], led=j)[0]
    return GainMapFit(gain_map, held_out, evidence, ratio)


def _spread(rows: np.ndarray) -> np.ndarray:
    """At most :data:`MAX_ROWS_PER_LED` of ``rows``, evenly spaced in their order."""
    if rows.size <= MAX_ROWS_PER_LED:
        return rows
    return rows[np.linspace(0, rows.size - 1, MAX_ROWS_PER_LED).round().astype(np.intp)]


def _kernel(a: FloatArray, b: FloatArray, scale: float) -> FloatArray:
    squared = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=-1)
    return np.asarray(np.exp(-0.5 * squared / scale**2))
