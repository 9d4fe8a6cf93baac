"""A survey's measurement of each LED's beam (a stage of the survey calibration, after the
Lambertian fit of :mod:`app.vlp._calibration_fit`; inputs already validated)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ._calibration_fit import LedFit, LedRows
from .beams import Beam, beam_arrays
from .typing import FloatArray

__all__ = ["MIN_ROWS_FOR_BEAM", "measured_beam", "with_beam"]

# Detected rows in an LED's view needed to measure its beam (BEAM_TERMS parameters more
# than the Lambertian order).
MIN_ROWS_FOR_BEAM = 16
# A measured beam is the Lambertian one times exp(sum_k a_k u^k), u = 1 - cos(alpha), k = 1..3:
# smooth, flat on the axis, and as many parameters as a survey's tens of rows per LED carry.
BEAM_TERMS = 3
# A measured beam that stays within this (log) fraction of the Lambertian one over the
# surveyed angles is not kept: a survey without noise would otherwise fit its round-off.
MIN_BEAM_CHANGE = 0.01
# Its table: every 5 degrees from the axis to 90.
BEAM_TABLE_STEP_DEG = 5.0


def measured_beam(rows: LedRows, fit: LedFit, rho: FloatArray) -> Beam | None:
    """The LED's beam as the survey shows it, or None when the survey cannot tell it from
    the fitted Lambertian one.

    The detected rows in view give ``ln(a / f)`` (measured over the fitted model) against
    ``u = 1 - cos(alpha)`` of the fitted LED; a weighted least-squares polynomial
    ``a_0 + sum_k a_k u^k`` (:data:`BEAM_TERMS`; weights ``a``, as ``var(ln a) ~ 1 / a^2``)
    is the correction, ``a_0`` a change of amplitude. It is kept when it lowers the
    amplitudes' squared misfit by more than chance would (``p + 3 sqrt(2 p)`` noise
    variances, ``p = BEAM_TERMS + 1``, the noise from the fit without it, as the tilt's
    gate), and when it moves the beam by more than :data:`MIN_BEAM_CHANGE` somewhere in the
    surveyed angles. The table is ``cos^m(alpha) exp(sum_k a_k u^k)`` every
    :data:`BEAM_TABLE_STEP_DEG`, the correction held at its value at the widest angle the
    survey saw beyond it. Needs :data:`MIN_ROWS_FOR_BEAM` rows; an LED whose layout gives a
    beam keeps it.
    """
    if rows.beam is not None or rows.detected_in_view() < MIN_ROWS_FOR_BEAM:
        return None
    modelled = rows.model(fit.ratio, fit.order, fit.shift, rho, fit.tilt)
    _, _, dist_sq, view, facing, _ = rows.geometry(fit.shift, fit.tilt)
    used = view & ~rows.is_censored & (modelled > 0) & (rows.amplitudes > 0)
    n_used = int(np.count_nonzero(used))
    n_terms = BEAM_TERMS + 1
    if n_used < MIN_ROWS_FOR_BEAM:
        return None
    measured = rows.amplitudes[used]
    u = 1.0 - facing[used] / np.sqrt(dist_sq[used])
    design = u[:, None] ** np.arange(n_terms)[None, :]
    weights = measured / float(np.max(measured))
    target = np.log(measured / modelled[used])
    coefficients, *_ = np.linalg.lstsq(design * weights[:, None], target * weights, rcond=None)
    corrected = modelled[used] * np.exp(design @ coefficients)
    cost_before = float(np.sum((measured - modelled[used]) ** 2))
    cost_after = float(np.sum((measured - corrected) ** 2))
    dof = max(n_used - int(np.count_nonzero(fit.free)), 1)
    chance = n_terms + 3.0 * math.sqrt(2.0 * n_terms)
    if not cost_before - cost_after > chance * cost_before / dof:
        return None
    if float(np.max(np.abs(design[:, 1:] @ coefficients[1:]))) < MIN_BEAM_CHANGE:
        return None  # within a percent of the Lambertian beam: nothing worth a table
    angles = np.arange(0.0, 90.0 + BEAM_TABLE_STEP_DEG / 2, BEAM_TABLE_STEP_DEG)
    cosines = np.cos(np.radians(angles)).clip(0.0, 1.0)
    held = np.minimum(1.0 - cosines, float(np.max(u)))
    shape = np.exp((held[:, None] ** np.arange(1, n_terms)[None, :]) @ coefficients[1:])
    values = cosines**fit.order * shape
    values[-1] = 0.0  # cos(90 degrees)^m: exactly 0, not 1e-17^m
    return Beam(tuple(float(a) for a in angles), tuple(float(v) for v in values))


def with_beam(rows: LedRows, beam: Beam) -> LedRows:
    """The rows of the LED with ``beam`` (order 0; its base divided by the beam's
    hemisphere integral, as :func:`app.vlp.channel.led_constants` does)."""
    return replace(rows, base=rows.base / beam.hemisphere_integral(), beam=beam_arrays([beam]))
