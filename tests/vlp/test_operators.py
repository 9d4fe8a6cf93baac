"""Psi as an operator: dot test and agreement with the explicit matrix."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.errors import MeasurementError
from app.vlp.fingerprints import Fingerprint
from app.vlp.operators import CorrelationOperator, dottest


@pytest.fixture(params=["paper", "mixed"])
def fingerprint(
    request: pytest.FixtureRequest, paper_fingerprint: Fingerprint, mixed_fingerprint: Fingerprint
) -> Fingerprint:
    return paper_fingerprint if request.param == "paper" else mixed_fingerprint


@pytest.mark.parametrize("seed", range(5))
def test_dot_test(fingerprint: Fingerprint, seed: int) -> None:
    assert dottest(fingerprint.correlation_operator(), rng=seed)


def test_dot_test_detects_a_wrong_adjoint(fingerprint: Fingerprint) -> None:
    class Broken(CorrelationOperator):
        def rmatvec(self, residual: np.ndarray) -> np.ndarray:
            return 1.01 * super().rmatvec(residual)

    assert not dottest(Broken(fingerprint.scaled_gains()), rng=0)


def test_matches_explicit_matrix(fingerprint: Fingerprint, rng: np.random.Generator) -> None:
    operator = fingerprint.correlation_operator()
    psi = fingerprint.correlation_matrix()
    m = fingerprint.n_leds
    assert operator.shape == psi.shape == (m * (m + 1) // 2, fingerprint.n_cells)
    theta = rng.standard_normal(fingerprint.n_cells)
    residual = rng.standard_normal(operator.shape[0])
    scale = float(np.max(np.abs(psi)))
    assert_allclose(operator.matvec(theta), psi @ theta, rtol=1e-10, atol=1e-12 * scale)
    assert_allclose(operator.rmatvec(residual), psi.T @ residual, rtol=1e-10, atol=1e-12 * scale)


def test_shape_errors(fingerprint: Fingerprint) -> None:
    # A wrong shape here is the caller's programming error, not a client's bad measurement.
    operator = fingerprint.correlation_operator()
    with pytest.raises(ValueError, match="shape") as matvec:
        operator.matvec(np.ones(fingerprint.n_cells + 1))
    with pytest.raises(ValueError, match="shape") as rmatvec:
        operator.rmatvec(np.ones(3))
    assert not isinstance(matvec.value, MeasurementError)
    assert not isinstance(rmatvec.value, MeasurementError)
