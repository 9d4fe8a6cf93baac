"""Nuisances fitted only where the detected LEDs support them (solvers/_data_support.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from app.vlp.layout import Layout
from app.vlp.solvers._data_support import (
    MIN_RESIDUAL_DOF,
    detected_leds,
    leaves_dof,
    supports_nuisance,
)
from app.vlp.solvers.gridless import GridlessOptions
from app.vlp.solvers.gridless.channel import ChannelKernel
from app.vlp.solvers.gridless.options import nuisance_priors
from app.vlp.solvers.gridless.terminals import fit_terminal, los_with_normal


def test_detected_leds_are_those_above_three_noise_sd() -> None:
    amplitudes = np.array([0.0, 0.02, 0.05, 0.5, 1.0])
    assert detected_leds(amplitudes, None) == 4  # noise unknown: every nonzero amplitude
    assert detected_leds(amplitudes, 0.01**2) == 3  # 0.02 < 3 x 0.01 < 0.05
    per_led = np.array([1.0, 1.0, 1.0, 1.0, 0.01]) ** 2
    assert detected_leds(amplitudes, per_led) == 1


def test_the_count_rule_and_the_evidence_price() -> None:
    # 5 LEDs, x, y and a gain fitted: a 2-component tilt leaves nothing to test it with.
    assert not leaves_dof(5, 3, 2)
    assert leaves_dof(3 + 2 + MIN_RESIDUAL_DOF, 3, 2)
    assert not supports_nuisance(1e6, 5, 3, 2, chance=8.0)
    # Enough LEDs: the larger of the chance level and the BIC price 2 ln n decides.
    assert supports_nuisance(8.1, 16, 3, 2, chance=8.0)
    assert not supports_nuisance(7.9, 16, 3, 2, chance=8.0)
    price = 2 * math.log(400)
    assert price > 8.0 and not supports_nuisance(price - 0.1, 400, 3, 2, chance=8.0)
    assert supports_nuisance(price + 0.1, 400, 3, 2, chance=8.0)


def _tilted_amplitudes(kernel: ChannelKernel, point: np.ndarray, tilt_deg: float) -> np.ndarray:
    tilt = math.radians(tilt_deg)
    normal = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    return los_with_normal(kernel, np.array([*point, 0.85]), normal)[0]


@pytest.mark.parametrize(("n_leds", "fits_tilt"), [(16, True), (5, False)])
def test_a_strong_tilt_is_fitted_only_where_the_leds_leave_room_for_it(
    paper_room: Layout, n_leds: int, fits_tilt: bool
) -> None:
    # The paper room with all 16 LEDs, or 5 of them (four corners and one inner LED).
    keep = list(range(16)) if n_leds == 16 else [0, 3, 5, 12, 15]
    room = replace(paper_room, leds=tuple(paper_room.leds[i] for i in keep))
    kernel = ChannelKernel(room, scale=1.0)
    priors = nuisance_priors(room, GridlessOptions())
    point = np.array([1.7, 2.2])
    clean = _tilted_amplitudes(kernel, point, 25.0)
    sigma = 0.002 * float(np.max(clean))
    amplitudes = clean + sigma * np.random.default_rng(3).standard_normal(clean.shape)
    fit = fit_terminal(
        kernel,
        amplitudes,
        point[None, :],
        priors=priors,
        sigma2=sigma**2,
        height=0.85,
        normal=None,
        tilt_sd=0.1,
    )
    assert detected_leds(amplitudes, sigma**2) == n_leds
    assert fit.free_tilt is fits_tilt
