"""Survey data for the calibration: measured pilot amplitudes at surveyed points.

An admin walks a receiver over surveyed points on the receivers' plane and records, per LED,
the received pilot amplitude (see :mod:`app.vlp.calibration` for the fit). This module holds
the validated container, its construction from plain rows, the check against a layout and a
simulator of surveys for tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .channel import channel_gains
from .errors import MeasurementError
from .layout import Layout
from .reflections import diffuse_gains
from .rng import RandomState, as_generator
from .typing import FloatArray, IntArray

__all__ = ["Survey", "check_survey", "simulate_survey", "survey_from_rows"]


@dataclass(frozen=True)
class Survey:
    """Measured pilot amplitudes at surveyed points, one row per (point, LED) pair.

    Parameters
    ----------
    points : ndarray of shape (S, 2)
        Receiver positions ``(x, y)``, metres, on the receivers' plane.
    led_indices : ndarray of shape (S,)
        Index ``i`` of the LED each amplitude belongs to (0-based, layout order).
    amplitudes : ndarray of shape (S,)
        Measured pilot amplitude ``a`` (same unit as ``h x``; may be slightly negative from
        noise); NaN where the LED was not detected (below the receiver's detection floor).
    detection_floor : float, default=None
        The survey receiver's detection floor (same unit); None: the weakest detected
        amplitude of the survey (one receiver walks the whole survey).

    Raises
    ------
    MeasurementError
        On wrong shapes, infinite values, no detected row at all or non-integer LED indices;
        ``field`` names the input (``"points"``, ``"led_indices"``, ``"amplitudes"``).
    """

    points: FloatArray
    led_indices: IntArray
    amplitudes: FloatArray
    detection_floor: float | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] < 1:
            raise MeasurementError(
                f"points must have shape (S, 2) with S >= 1, got {points.shape}", field="points"
            )
        n_rows = points.shape[0]
        raw_indices = np.asarray(self.led_indices)
        amplitudes = np.asarray(self.amplitudes, dtype=np.float64)
        for name, array in (("led_indices", raw_indices), ("amplitudes", amplitudes)):
            if array.shape != (n_rows,):
                raise MeasurementError(
                    f"{name} must have shape ({n_rows},) like points, got {array.shape}", field=name
                )
        _require_finite(points, "points")
        _require_finite(np.where(np.isnan(amplitudes), 0.0, amplitudes), "amplitudes")
        if np.all(np.isnan(amplitudes)):
            raise MeasurementError(
                "every amplitude is not detected (NaN): nothing to fit", field="amplitudes"
            )
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "led_indices", _as_indices(raw_indices))
        object.__setattr__(self, "amplitudes", amplitudes)

    @property
    def n_rows(self) -> int:
        """Number of survey rows S."""
        return int(self.amplitudes.shape[0])

    @property
    def detected(self) -> npt.NDArray[np.bool_]:
        """(S,) bool: the row's LED was detected (its amplitude is a number)."""
        return np.asarray(~np.isnan(self.amplitudes))

    @property
    def floor(self) -> float:
        """The detection floor: :attr:`detection_floor`, else the weakest detected amplitude."""
        if self.detection_floor is not None:
            return float(self.detection_floor)
        return float(np.min(self.amplitudes[self.detected]))


def survey_from_rows(rows: FloatArray) -> Survey:
    """A :class:`Survey` from rows ``(x, y, led_index, amplitude)``, ndarray of shape (S, 4)
    (amplitude NaN: not detected)."""
    table = np.asarray(rows, dtype=np.float64)
    if table.ndim != 2 or table.shape[1] != 4:
        raise MeasurementError(
            f"survey rows must have shape (S, 4): x, y, led index, amplitude; got {table.shape}",
            field="rows",
        )
    return Survey(points=table[:, :2], led_indices=_as_indices(table[:, 2]), amplitudes=table[:, 3])


def simulate_survey(
    layout: Layout,
    points: FloatArray,
    noise_std: float = 0.0,
    *,
    rng: RandomState = None,
    receiver_gain: float = 1.0,
    element_size_m: float | None = None,
) -> Survey:
    """Survey every LED at every point of a (true) layout, with Gaussian amplitude noise.

    Parameters
    ----------
    layout : Layout
        The true room (perturbed amplitudes, angles and positions as the real LEDs are); when
        its ``room.reflectance`` is set, the first diffuse bounce is added
        (:func:`app.vlp.reflections.diffuse_gains`).
    points : ndarray of shape (P, 2)
        Surveyed positions, metres, on the receivers' plane.
    noise_std : float, default=0.0
        Standard deviation of the additive noise on each amplitude.
    rng : Generator, int or None
    receiver_gain : float, default=1.0
        The survey receiver's gain relative to the layout's receiver (e.g. one that drifted).
    element_size_m : float, default=None
        Largest quadrature cell of the reflections (the module's default when None).

    Returns
    -------
    Survey
        S = P * M rows, point-major (rows ``k * M .. k * M + M - 1`` belong to point k).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    gains = channel_gains(layout, pts)
    if layout.room.reflectance is not None:
        xyz = np.column_stack((pts, np.full(pts.shape[0], layout.grid.receiver_height)))
        gains = gains + diffuse_gains(layout, xyz, element_size_m=element_size_m)
    clean = receiver_gain * gains * layout.pilot_amplitudes[:, None]  # (M, P)
    noisy = clean + noise_std * as_generator(rng).standard_normal(clean.shape)
    n_leds = layout.n_leds
    return Survey(
        points=np.repeat(pts, n_leds, axis=0),
        led_indices=np.tile(np.arange(n_leds, dtype=np.intp), pts.shape[0]),
        amplitudes=noisy.T.ravel(),
    )


def check_survey(layout: Layout, survey: Survey) -> None:
    """Check that a survey fits a layout: LED indices in range, points inside the room.

    Raises
    ------
    MeasurementError
        ``field="led_indices"`` for an index outside ``[0, M)``, ``field="points"`` for a
        point outside the room; the message names the first offending row.
    """
    bad = np.flatnonzero((survey.led_indices < 0) | (survey.led_indices >= layout.n_leds))
    if bad.size:
        raise MeasurementError(
            f"led_indices[{int(bad[0])}] = {int(survey.led_indices[bad[0]])} is not an LED "
            f"index in [0, {layout.n_leds})",
            field="led_indices",
        )
    x, y = survey.points[:, 0], survey.points[:, 1]
    outside = np.flatnonzero((x < 0) | (x > layout.room.length) | (y < 0) | (y > layout.room.width))
    if outside.size:
        k = int(outside[0])
        raise MeasurementError(
            f"points[{k}] = ({x[k]!r}, {y[k]!r}) m lies outside the room "
            f"[0, {layout.room.length!r}] x [0, {layout.room.width!r}]",
            field="points",
        )


# -- private functions ---------------------------------------------------------------------------
def _require_finite(array: FloatArray, name: str) -> None:
    bad = np.flatnonzero(~np.isfinite(array.reshape(array.shape[0], -1)).all(axis=1))
    if bad.size:
        raise MeasurementError(f"{name} must be finite; row {int(bad[0])} is not", field=name)


def _as_indices(raw: npt.ArrayLike) -> IntArray:
    values = np.asarray(raw, dtype=np.float64)
    _require_finite(values, "led_indices")
    if np.any(values != np.round(values)):
        raise MeasurementError("led_indices must be whole numbers", field="led_indices")
    return values.astype(np.intp)
