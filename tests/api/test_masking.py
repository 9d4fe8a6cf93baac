"""Room-sized measurements mapped onto a fingerprint with masked LEDs."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.api.errors import InvalidInput
from app.api.masking import drop_masked_leds
from app.schemas import Measurement
from app.vlp.measurements import vech

MASKED = (1, 4)
N_ROOM = 6


@pytest.fixture
def amplitudes() -> np.ndarray:
    return np.random.default_rng(0).uniform(0.1, 1.0, (3, N_ROOM))


def _kept() -> list[int]:
    return [i for i in range(N_ROOM) if i not in MASKED]


def test_upper_triangle_keeps_the_sub_matrix_triangle(amplitudes: np.ndarray) -> None:
    correlation = amplitudes.T @ amplitudes
    body = Measurement(correlation=vech(correlation).tolist())
    out = drop_masked_leds(body, MASKED, N_ROOM - len(MASKED))
    expected = vech(correlation[np.ix_(_kept(), _kept())])
    assert_allclose(np.asarray(out.correlation), expected, rtol=0, atol=0)


def test_full_matrix_power_and_terminals(amplitudes: np.ndarray) -> None:
    n_kept = N_ROOM - len(MASKED)
    correlation = amplitudes.T @ amplitudes
    full = drop_masked_leds(Measurement(correlation=correlation.tolist()), MASKED, n_kept)
    assert_allclose(np.asarray(full.correlation), correlation[np.ix_(_kept(), _kept())])
    power = (amplitudes**2).sum(axis=0)
    out = drop_masked_leds(Measurement(power=power.tolist()), MASKED, n_kept)
    assert out.power == power[_kept()].tolist()
    terminals = [{"id": f"t{k}", "amplitudes": row.tolist()} for k, row in enumerate(amplitudes)]
    body = Measurement.model_validate({"terminals": terminals})
    out = drop_masked_leds(body, MASKED, n_kept)
    assert out.terminals is not None
    assert [t.amplitudes for t in out.terminals] == amplitudes[:, _kept()].tolist()
    assert [t.id for t in out.terminals] == ["t0", "t1", "t2"]


def test_fingerprint_sized_input_passes_and_other_sizes_are_refused() -> None:
    kept_sized = Measurement(power=[1.0] * (N_ROOM - len(MASKED)))
    assert drop_masked_leds(kept_sized, MASKED, N_ROOM - len(MASKED)) == kept_sized
    with pytest.raises(InvalidInput):
        drop_masked_leds(Measurement(power=[1.0] * 5), MASKED, N_ROOM - len(MASKED))
    unmasked = Measurement(power=[1.0] * N_ROOM)
    assert drop_masked_leds(unmasked, (), N_ROOM) is unmasked
