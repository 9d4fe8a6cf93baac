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
    summed_terminals,
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


@pytest.mark.parametrize("n_terminals", [1, 2, 7, 15])
def test_summed_terminals_is_the_rank_of_a_sum_of_outer_products(
    n_terminals: int, rng: np.random.Generator
) -> None:
    # Amplitudes of any scale and spread: the rank does not care.
    amplitudes = rng.lognormal(-3.0, 1.0, size=(n_terminals, 16))
    measurement = measurement_from_amplitudes(amplitudes, "correlation", 16)
    assert summed_terminals(measurement) == n_terminals
    # An independent count: numpy's own matrix rank of the same matrix.
    assert np.linalg.matrix_rank(measurement.correlation()) == n_terminals


def test_summed_terminals_says_nothing_where_the_spectrum_does_not(
    rng: np.random.Generator,
) -> None:
    amplitudes = rng.uniform(0.1, 1.0, size=(4, 16))
    correlation = correlation_from_amplitudes(amplitudes)
    # As many terminals as LEDs: full rank.
    full = measurement_from_amplitudes(rng.uniform(0.1, 1.0, size=(16, 16)), "correlation", 16)
    # Averaged over noisy samples: the noise fills the spectrum.
    averaged = measurement_from_correlation(correlation + 1e-4 * np.eye(16), 16)
    # Rounded in transit to 6 significant digits: the null space is no longer round-off.
    rounded = measurement_from_correlation(
        np.vectorize(lambda value: float(f"{value:.6g}"))(correlation), 16
    )
    # Not positive semi-definite (a symmetric off-diagonal change): no sum of outer products.
    swap = np.zeros((16, 16))
    swap[0, 1] = swap[1, 0] = 1e-3
    indefinite = measurement_from_correlation(correlation + swap, 16)
    power = measurement_from_amplitudes(amplitudes, "power", 16)
    for measurement in (full, averaged, rounded, indefinite, power):
        assert summed_terminals(measurement) is None


def _plain_correlation(correlation: object, n_leds: int) -> np.ndarray:
    """The correlation rules in plain NumPy, one whole-array step each: the checks as the
    contract states them, in its order, and the symmetrised matrix's upper triangle."""

    def refuse(message: str) -> MeasurementError:
        return MeasurementError(message, field="correlation")

    try:
        values = np.asarray(correlation, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise refuse("correlation must contain only numbers") from exc
    if not np.all(np.isfinite(values)):
        raise refuse("correlation contains NaN or infinite values")
    largest = float(np.max(np.abs(values))) if values.size else 0.0
    if largest > 1e100:
        raise refuse(
            f"correlation values must be at most {1e100:.0e} in magnitude, got {largest:.3g}"
        )
    if 0.0 < largest < 1e-100:
        raise refuse(
            f"correlation is below {1e-100:.0e} everywhere (largest {largest:.3g}): "
            "no pilot was received"
        )
    length = n_leds * (n_leds + 1) // 2
    rows, cols = np.triu_indices(n_leds)
    if values.shape == (n_leds, n_leds):
        if np.max(np.abs(values - values.T)) > 1e-6 * max(largest, 1e-300):
            raise refuse("correlation matrix must be symmetric")
        values = (0.5 * (values + values.T))[rows, cols]
    elif values.shape != (length,):
        raise refuse(
            f"correlation must be a {n_leds} x {n_leds} matrix or its {length} "
            f"upper-triangle entries, got shape {values.shape}"
        )
    diagonal = values[rows == cols]
    if np.any(diagonal < 0):
        raise refuse("correlation diagonal entries must be >= 0")
    if not np.any(diagonal > 0):
        raise refuse("correlation is all zero on its diagonal: no pilot was received")
    return values


def _correlation_inputs(rng: np.random.Generator, n_leds: int) -> list[object]:
    """Valid and invalid correlation inputs of M LEDs, as arrays and as JSON's lists."""
    amplitudes = rng.uniform(0.0, 2.0, size=(int(rng.integers(1, 6)), n_leds))
    matrix = amplitudes.T @ amplitudes * 10.0 ** rng.uniform(-30, 30)
    cases: list[object] = [matrix, vech(matrix)]
    noisy = matrix * (1 + rng.normal(0.0, 1e-9, matrix.shape))  # asymmetric within tolerance
    cases.append(noisy)
    if n_leds > 1:
        skewed = matrix.copy()
        skewed[0, 1] *= 1.01  # beyond it
        cases.append(skewed)
        for ratio in (0.5e-6, 1.5e-6):  # either side of the tolerance, near it
            edge = matrix.copy()
            edge[0, 1] += ratio * np.max(matrix)
            cases.append(edge)
    signed = matrix.copy()
    signed[-1, -1] = -abs(signed[-1, -1]) - 1.0
    cases += [signed, vech(signed), np.zeros_like(matrix), np.zeros(vech_length(n_leds))]
    off_diagonal = matrix - np.diag(np.diag(matrix))  # no pilot on the diagonal
    cases += [off_diagonal, vech(off_diagonal)]
    for bad in (np.nan, np.inf, -np.inf, 1e101, -1e101):
        spoiled = matrix.copy()
        spoiled.flat[rng.integers(matrix.size)] = bad
        cases.append(spoiled)
    cases += [matrix * 1e-120, matrix[:, :-1], vech(matrix)[:-1], matrix[None], np.ones(0)]
    cases += [case.tolist() for case in list(cases) if isinstance(case, np.ndarray)]
    cases += [
        matrix.tolist(),
        vech(matrix).tolist(),
        [["a"] * n_leds] * n_leds,
        [[1.0] * n_leds] * (n_leds - 1) + [[1.0]],  # ragged
        [None] * vech_length(n_leds),
        np.asfortranarray(matrix),
        matrix.astype(np.float32),
        5.0,
    ]
    return cases


@pytest.mark.parametrize("n_leds", [1, 2, 3, 5, 16])
def test_correlation_measurement_equals_the_plain_rules(
    n_leds: int, rng: np.random.Generator
) -> None:
    """Same values, bit for bit, or the same error, on random valid and invalid inputs."""
    outcomes = []
    for _ in range(20):
        for case in _correlation_inputs(rng, n_leds):
            try:
                expected = _plain_correlation(case, n_leds)
            except MeasurementError as error:
                with pytest.raises(MeasurementError) as info:
                    measurement_from_correlation(case, n_leds)
                assert (info.value.message, info.value.field) == (error.message, error.field)
                outcomes.append(" ".join(error.message.split(" ")[:4]))
                continue
            measurement = measurement_from_correlation(case, n_leds)
            assert measurement.model == "correlation"
            assert measurement.n_leds == n_leds
            assert measurement.values.dtype == np.float64
            assert_array_equal(measurement.values, expected, strict=True)
            outcomes.append("valid")
    assert "valid" in outcomes
    # valid inputs and each of the eight rules (one LED: no asymmetry)
    assert len(set(outcomes)) == (9 if n_leds > 1 else 8)
