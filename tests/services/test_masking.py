"""Room-sized measurements mapped onto a fingerprint with masked LEDs."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.schemas import Measurement
from app.services.masking import drop_masked_leds, fit_to_fingerprint
from app.vlp.errors import MeasurementError
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
    with pytest.raises(MeasurementError) as refused:
        drop_masked_leds(Measurement(power=[1.0] * 5), MASKED, N_ROOM - len(MASKED))
    assert refused.value.field == "power"
    unmasked = Measurement(power=[1.0] * N_ROOM)
    assert drop_masked_leds(unmasked, (), N_ROOM) is unmasked


def test_fit_to_fingerprint_drops_masked_entries_and_names_the_field() -> None:
    room_sized = [float(i) for i in range(N_ROOM)]
    assert fit_to_fingerprint(room_sized, MASKED, N_ROOM - len(MASKED), field="amplitudes") == [
        0.0,
        2.0,
        3.0,
        5.0,
    ]
    assert fit_to_fingerprint([1.0, 2.0], (), 2, field="amplitudes") == [1.0, 2.0]
    with pytest.raises(MeasurementError, match="expected 3 amplitudes") as refused:
        fit_to_fingerprint([1.0, 2.0], (), 3, field="terminals[1].amplitudes")
    assert refused.value.field == "terminals[1].amplitudes"
    with pytest.raises(MeasurementError, match=f"{N_ROOM} entries .* or 4"):
        fit_to_fingerprint([1.0] * 5, MASKED, N_ROOM - len(MASKED), field="power")
