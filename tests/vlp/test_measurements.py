"""Measurements: vech, aggregation, and validation errors that name the field."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp.errors import MeasurementError
from app.vlp.measurements import (
    correlation_from_amplitudes,
    measurement_from_amplitudes,
    measurement_from_correlation,
    measurement_from_power,
    noise_atom,
    power_from_amplitudes,
    unvech,
    vech,
    vech_length,
)


@pytest.mark.parametrize("n_leds", [1, 2, 5, 16])
def test_vech_round_trip(n_leds: int, rng: np.random.Generator) -> None:
    base = rng.standard_normal((n_leds, n_leds))
    symmetric = base + base.T
    values = vech(symmetric)
    assert values.shape == (vech_length(n_leds),)
    expected = [symmetric[i, l_] for i in range(n_leds) for l_ in range(i, n_leds)]
    assert_array_equal(values, expected)
    assert_array_equal(unvech(values, n_leds), symmetric)


def test_unvech_wrong_length() -> None:
    with pytest.raises(MeasurementError) as info:
        unvech(np.ones(5), 3)
    assert info.value.field == "correlation"


def test_aggregation_equals_direct_sums(rng: np.random.Generator) -> None:
    amps = rng.standard_normal((4, 6))
    power = power_from_amplitudes(amps)
    corr = correlation_from_amplitudes(amps)
    for i in range(6):
        assert power[i] == pytest.approx(sum(amps[k, i] ** 2 for k in range(4)))
        for l_ in range(6):
            assert corr[i, l_] == pytest.approx(sum(amps[k, i] * amps[k, l_] for k in range(4)))
    by_power = measurement_from_amplitudes(amps, "power", 6)
    by_corr = measurement_from_amplitudes(amps, "correlation", 6)
    assert_allclose(by_power.values, power)
    assert_allclose(by_corr.correlation(), corr)
    assert by_corr.n_leds == 6 and by_corr.model == "correlation"


def test_correlation_accepts_matrix_or_vech(rng: np.random.Generator) -> None:
    amps = rng.standard_normal((3, 4))
    corr = correlation_from_amplitudes(amps)
    full = measurement_from_correlation(corr, 4)
    packed = measurement_from_correlation(vech(corr), 4)
    assert_allclose(full.values, packed.values)
    assert_allclose(full.values, vech(corr))


def test_noise_atom() -> None:
    assert_array_equal(noise_atom("power", 3), np.ones(3))
    assert_array_equal(noise_atom("correlation", 3), [1, 0, 0, 1, 0, 1])


@pytest.mark.parametrize(
    ("call", "field", "message"),
    [
        (lambda: measurement_from_power([1.0, np.nan, 1.0], 3), "power", "NaN"),
        (lambda: measurement_from_power([1.0, np.inf, 1.0], 3), "power", "infinite"),
        (lambda: measurement_from_power([1.0, 2.0], 3), "power", "3 entries"),
        (lambda: measurement_from_power([1.0, -2.0, 1.0], 3), "power", ">= 0"),
        (lambda: measurement_from_power([0.0, 0.0, 0.0], 3), "power", "all zero"),
        (lambda: measurement_from_power(["a", 1, 2], 3), "power", "numbers"),
        (lambda: measurement_from_correlation(np.ones(5), 3), "correlation", "upper-triangle"),
        (
            lambda: measurement_from_correlation([[1.0, 2.0], [0.0, 1.0]], 2),
            "correlation",
            "symmetric",
        ),
        (lambda: measurement_from_correlation(np.zeros((2, 2)), 2), "correlation", "all zero"),
        (lambda: measurement_from_correlation([[-1.0, 0.0], [0.0, 1.0]], 2), "correlation", ">= 0"),
        (
            lambda: measurement_from_correlation([[np.nan, 0.0], [0.0, 1.0]], 2),
            "correlation",
            "NaN",
        ),
        (
            lambda: measurement_from_amplitudes(np.ones((2, 4)), "power", 3),
            "terminals",
            "3 entries",
        ),
        (
            lambda: measurement_from_amplitudes([[1.0, np.inf, 1.0]], "power", 3),
            "amplitudes",
            "NaN",
        ),
        (lambda: measurement_from_power([1.0, 2.0], 2).correlation(), "model", "power"),
    ],
    ids=[
        "nan",
        "inf",
        "length",
        "negative",
        "zero",
        "text",
        "corr-length",
        "asymmetric",
        "corr-zero",
        "corr-negative-diagonal",
        "corr-nan",
        "amps-length",
        "amps-inf",
        "power-has-no-correlation",
    ],
)
def test_validation_errors(call: object, field: str, message: str) -> None:
    with pytest.raises(MeasurementError, match=message) as info:
        call()  # type: ignore[operator]
    assert info.value.field == field
