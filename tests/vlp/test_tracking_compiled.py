"""The compiled filter step against its NumPy reference (:func:`predict` then :func:`update`)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from app.vlp._kernels import use_kernels
from app.vlp.tracking import N_MODELS, TrackBank, TrackerSettings
from app.vlp.tracking.filter import Update, floored_covariances, predict_update
from app.vlp.tracking.starts import consistent_runs, whitened_offsets


def _random_bank(rng: np.random.Generator, n: int) -> TrackBank:
    roots = rng.normal(0.0, 0.2, (n, N_MODELS, 4, 4))
    noise_var = rng.uniform(1e-4, 1e-2, n)
    noise_var[::3] = np.nan  # not learned yet
    stated_var = rng.uniform(1e-4, 1e-2, n)
    stated_var[::4] = np.nan
    return TrackBank(
        means=np.concatenate(
            (rng.uniform(0.0, 5.0, (n, N_MODELS, 2)), rng.normal(0.0, 2.0, (n, N_MODELS, 2))),
            axis=2,
        ),
        covariances=roots @ np.swapaxes(roots, -1, -2) + 1e-3 * np.eye(4),
        model_probabilities=rng.dirichlet([1.0, 1.0], n),
        times_s=rng.uniform(0.0, 1.0, n),
        wild=rng.integers(0, 3, n).astype(np.intp),
        noise_var=noise_var,
        stated_var=stated_var,
        offset=rng.normal(0.0, 2.0, (n, 2)),
    )


def _step(
    mode: str,
    bank: TrackBank,
    fixes: np.ndarray,
    noise: np.ndarray,
    learn: bool,
    inflate_chi2: float | None,
) -> Update:
    with use_kernels(mode):  # type: ignore[arg-type]
        return predict_update(
            bank, fixes, noise, 0.9, TrackerSettings(), learn=learn, inflate_chi2=inflate_chi2
        )


# A labelled step, and an anonymous one (no learning; inflation to the gate, or to the
# anonymous bound below it).
@pytest.mark.parametrize(
    ("learn", "inflate_chi2"),
    [(True, None), (False, None), (False, TrackerSettings().anonymous_inflate_chi2)],
)
def test_compiled_step_matches_the_numpy_reference(learn: bool, inflate_chi2: float | None) -> None:
    rng = np.random.default_rng(11)
    n = 60
    bank = _random_bank(rng, n)
    # Most fixes near the tracks, some far (wild: inflated, and restarting the tracks already
    # two wild fixes into a streak); some tracks are newer than the fix (no step back in time).
    fixes = bank.means[:, 0, :2] + rng.normal(0.0, 0.1, (n, 2))
    fixes[::5] += rng.uniform(1.0, 3.0, (fixes[::5].shape[0], 2))
    # Some far fixes continue a run: their previous offsets point the same way.
    bank.offset[::5] = 4.0
    roots = rng.normal(0.0, 0.05, (n, 2, 2))
    noise = roots @ np.swapaxes(roots, -1, -2) + 1e-4 * np.eye(2)
    reference = _step("reference", bank, fixes, noise, learn, inflate_chi2)
    compiled = _step("compiled", bank, fixes, noise, learn, inflate_chi2)
    assert np.any(reference.wild) and np.any(reference.restarted)
    stated = floored_covariances(noise, TrackerSettings())
    offsets = whitened_offsets(
        bank.means,
        bank.covariances,
        bank.noise_var,
        fixes,
        (stated[:, 0, 0] + stated[:, 1, 1]) / 2.0,
        np.maximum(0.9 - bank.times_s, 0.0),
        TrackerSettings(),
    )
    runs = consistent_runs(bank.offset, offsets, TrackerSettings())
    standing = bank.model_probabilities[:, 0] >= 0.5
    assert np.any(runs & standing & ~reference.restarted)
    assert np.any(bank.times_s > 0.9) and np.any(bank.times_s < 0.9)
    assert_array_equal(compiled.wild, reference.wild)
    assert_array_equal(compiled.restarted, reference.restarted)
    assert_array_equal(compiled.bank.wild, reference.bank.wild)
    for name in (
        "means",
        "covariances",
        "model_probabilities",
        "times_s",
        "noise_var",
        "stated_var",
        "offset",
    ):
        ours, theirs = getattr(compiled.bank, name), getattr(reference.bank, name)
        scale = np.max(np.abs(theirs))
        assert_allclose(ours, theirs, rtol=1e-10, atol=1e-10 * scale, err_msg=name)
