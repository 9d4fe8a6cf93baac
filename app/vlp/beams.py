"""Tabulated LED beams: relative radiant intensity by the angle off the LED's axis.

A luminaire's photometric file (IES LM-63, EULUMDAT) gives its intensity at a list of angles;
measured ceiling LEDs are often far from Lambertian (a batwing beam is flat to 45 degrees and
more). A :class:`Beam` takes such a table and is the LED's emission pattern ``I(alpha)`` in
the channel instead of ``cos^m(alpha)``:

.. math::

    h = \\frac{A\\, G_f\\, G_c}{2 \\pi \\int_0^1 I\\, dc}\\; I(c)\\, \\frac{\\cos\\phi}{d^2},
    \\qquad c = \\cos\\alpha,

normalised, as the Lambertian ``(m + 1) / (2 pi)`` is, so that the LED emits its pilot
amplitude over the hemisphere (``dOmega = 2 pi dc``): a table of ``cos^m`` gives the
Lambertian gain back. The table's scale is therefore free (candela or relative values alike).

Between the table's angles the intensity is the monotone piecewise-cubic (PCHIP) interpolant
in ``c``, so it is continuously differentiable, never negative and never overshoots the
table; beyond the table's last angle it is 0.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .constants import MAX_BEAM_ANGLES
from .errors import GeometryError
from .typing import FloatArray

__all__ = ["MAX_BEAM_ANGLES", "Beam", "BeamArrays", "beam_arrays", "evaluate_beams"]


@dataclass(frozen=True)
class Beam:
    """An LED's relative intensity at angles off its axis (degrees, from 0, increasing).

    Raises
    ------
    GeometryError
        On fewer than two angles, angles that do not start at 0, do not increase or pass 90,
        a negative or non-finite intensity, or a zero intensity on the axis. ``field`` names
        the offending input relative to the beam (``"angles_deg"``, ``"relative_intensity"``).
    """

    angles_deg: tuple[float, ...]
    relative_intensity: tuple[float, ...]

    def __post_init__(self) -> None:
        angles, values = self.angles_deg, self.relative_intensity
        if not 2 <= len(angles) <= MAX_BEAM_ANGLES:
            raise GeometryError(
                f"a beam needs 2 to {MAX_BEAM_ANGLES} angles, got {len(angles)}",
                field="angles_deg",
            )
        if len(values) != len(angles):
            raise GeometryError(
                f"a beam needs one relative_intensity per angle: {len(angles)} angles, "
                f"{len(values)} intensities",
                field="relative_intensity",
            )
        if not all(math.isfinite(a) for a in angles) or angles[0] != 0.0 or angles[-1] > 90.0:
            raise GeometryError(
                f"beam angles must start at 0 and end at most at 90 degrees, got {list(angles)}",
                field="angles_deg",
            )
        if any(b <= a for a, b in itertools.pairwise(angles)):
            raise GeometryError(
                f"beam angles must increase, got {list(angles)}", field="angles_deg"
            )
        if not all(math.isfinite(v) and v >= 0 for v in values) or values[0] <= 0:
            raise GeometryError(
                "beam relative_intensity must be finite numbers >= 0, positive on the axis "
                f"(angle 0), got {list(values)}",
                field="relative_intensity",
            )

    @classmethod
    def lambertian(cls, order: float, step_deg: float = 5.0) -> Beam:
        """The table of ``cos^order`` from 0 to 90 degrees every ``step_deg``."""
        angles = np.arange(0.0, 90.0 + step_deg / 2, step_deg)
        values = np.cos(np.radians(angles)).clip(0.0, None) ** order
        return cls(tuple(float(a) for a in angles), tuple(float(v) for v in values))

    def knots(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The interpolant in ``c = cos(alpha)``: knots ``c`` (increasing), values and slopes
        ``dI/dc`` there, each of shape (n,), read-only; intensities scaled to 1 on the axis."""
        return self._interpolant

    @functools.cached_property
    def _interpolant(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        # Built once per beam: the reflections evaluate a beam for every receiver point.
        from scipy.interpolate import PchipInterpolator  # only layouts with beams need it

        cosines = np.cos(np.radians(np.asarray(self.angles_deg, dtype=np.float64)))[::-1]
        cosines[0] = max(cosines[0], 0.0)  # cos(90 degrees) is 6e-17
        values = np.asarray(self.relative_intensity, dtype=np.float64)[::-1]
        values = values / values[-1]
        slopes = np.asarray(PchipInterpolator(cosines, values).derivative()(cosines), np.float64)
        for array in (cosines, values, slopes):
            array.setflags(write=False)
        return cosines, values, slopes

    def hemisphere_integral(self) -> float:
        """``int_0^1 I(c) dc`` of the interpolant (its exact integral, segment by segment)."""
        cosines, values, slopes = self._interpolant
        width = np.diff(cosines)
        trapezoids = width * (values[:-1] + values[1:]) / 2
        return float(np.sum(trapezoids + width**2 * (slopes[:-1] - slopes[1:]) / 12))

    def to_mapping(self) -> dict[str, list[float]]:
        return {
            "angles_deg": list(self.angles_deg),
            "relative_intensity": list(self.relative_intensity),
        }


@dataclass(frozen=True)
class BeamArrays:
    """Every LED's beam as padded arrays for the kernels (LEDs without one: ``beamed``
    False and one dummy knot).

    ``knots``, ``values``, ``slopes`` (M, n): the interpolant in ``c`` of each beamed LED, its
    last ``counts[i]`` entries used (padding repeats the first knot at the front);
    ``counts`` (M,) int.
    """

    beamed: np.ndarray
    knots: FloatArray
    values: FloatArray
    slopes: FloatArray
    counts: np.ndarray


def beam_arrays(beams: Sequence[Beam | None]) -> BeamArrays:
    """Pad the LEDs' interpolants into :class:`BeamArrays`."""
    parts = [beam.knots() if beam is not None else None for beam in beams]
    width = max((p[0].size for p in parts if p is not None), default=1)
    shape = (len(beams), width)
    knots, values, slopes = np.ones(shape), np.ones(shape), np.zeros(shape)
    counts = np.ones(len(beams), dtype=np.int64)
    for i, part in enumerate(parts):
        if part is None:
            continue
        n = part[0].size
        # Pad at the front with the first knot (value 0 beyond it would be a jump; the
        # kernels never read the padding: they start at width - count).
        knots[i] = np.r_[np.full(width - n, part[0][0]), part[0]]
        values[i] = np.r_[np.full(width - n, part[1][0]), part[1]]
        slopes[i] = np.r_[np.zeros(width - n), part[2]]
        counts[i] = n
    beamed = np.array([beam is not None for beam in beams], dtype=bool)
    return BeamArrays(beamed, knots, values, slopes, counts)


def evaluate_beams(arrays: BeamArrays, cosines: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Intensity ``I(c)`` and ``dI/dc`` of each LED's beam at ``c`` (M, P).

    Rows of LEDs without a beam are 1 and 0; ``c`` above the axis' 1 reads the axis, below the
    table's last angle 0.
    """
    c = np.asarray(cosines, dtype=np.float64)
    intensity = np.ones_like(c)
    slope = np.zeros_like(c)
    width = arrays.knots.shape[1]
    for i in np.flatnonzero(arrays.beamed):
        start = width - int(arrays.counts[i])
        knots = arrays.knots[i, start:]
        values = arrays.values[i, start:]
        slopes = arrays.slopes[i, start:]
        row = np.minimum(c[i], 1.0)
        inside = row >= knots[0]
        cell = np.clip(np.searchsorted(knots, row, side="right") - 1, 0, knots.size - 2)
        h = knots[cell + 1] - knots[cell]
        t = (row - knots[cell]) / h
        y0, y1 = values[cell], values[cell + 1]
        m0, m1 = slopes[cell] * h, slopes[cell + 1] * h
        t2, t3 = t * t, t * t * t
        value = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0
        value += (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1
        derivative = ((6 * t2 - 6 * t) * y0 + (3 * t2 - 4 * t + 1) * m0) / h
        derivative += ((-6 * t2 + 6 * t) * y1 + (3 * t2 - 2 * t) * m1) / h
        intensity[i] = np.where(inside, np.maximum(value, 0.0), 0.0)
        slope[i] = np.where(inside, derivative, 0.0)
    return intensity, slope
