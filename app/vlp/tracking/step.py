"""One step of a room's tracks: every track predicted to the fixes' time and updated with
its fix (:mod:`.filter`'s predict and update, then :mod:`.starts`' runs), wild streaks
restarted; a compiled kernel (:mod:`._filter_compiled`) and its NumPy reference.
"""

from __future__ import annotations

import numpy as np

from ..typing import BoolArray, FloatArray
from .bank import TrackBank
from .filter import Update, floored_covariances, predict, updated_tracks, with_restarts
from .settings import TrackerSettings
from .starts import after_runs, whitened_offsets

__all__ = [
    "fix_offsets",
    "predict_update",
    "predict_update_kernel",
    "predict_update_reference",
]


def predict_update(
    bank: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
    *,
    learn: bool = True,
    inflate_chi2: float | FloatArray | None = None,
) -> Update:
    """Every track predicted to ``time_s`` (:func:`.filter.predict`) and updated with its
    fix (row ``k`` with fix ``k``, :func:`.filter.update` with ``inflate_chi2``, the time
    since the track's state as ``elapsed_s``).

    :func:`predict_update_kernel` while the compiled kernels are in use, else
    :func:`predict_update_reference`; then the restarts. The kernel engine is imported here,
    not at the top: numba loads with the first step, not with this module.
    """
    from .._kernels import dispatch

    updated, wild = dispatch(predict_update_kernel, predict_update_reference)(
        bank, positions, covariances, time_s, settings, learn, inflate_chi2
    )
    return with_restarts(updated, wild, positions, covariances, settings)


def predict_update_reference(
    bank: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
    learn: bool,
    inflate_chi2: float | FloatArray | None,
) -> tuple[TrackBank, BoolArray]:
    """:func:`predict_update` before the restarts, with the NumPy functions
    (:func:`.filter.predict`, then :func:`.filter.update`'s step and
    :func:`.starts.after_runs`): the updated tracks and which fixes were wild."""
    elapsed = np.maximum(time_s - bank.times_s, 0.0)
    offsets = fix_offsets(bank, positions, covariances, time_s, settings)
    predicted = predict(bank, np.full(bank.size, time_s), settings)
    updated, wild = updated_tracks(
        predicted,
        positions,
        covariances,
        settings,
        elapsed,
        learn=learn,
        inflate_chi2=inflate_chi2,
    )
    return after_runs(updated, bank, offsets, learn, settings), wild


def fix_offsets(
    bank: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
) -> FloatArray:
    """Each fix's offset from its track's last state, whitened as :func:`.starts.after_runs`
    reads it (:func:`whitened_offsets` with the fixes' floored mean variances)."""
    stated = floored_covariances(covariances, settings)
    return whitened_offsets(
        bank.means,
        bank.covariances,
        bank.noise_var,
        positions,
        (stated[:, 0, 0] + stated[:, 1, 1]) / 2.0,
        np.maximum(time_s - bank.times_s, 0.0),
        settings,
    )


def predict_update_kernel(
    bank: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
    learn: bool,
    inflate_chi2: float | FloatArray | None,
) -> tuple[TrackBank, BoolArray]:
    """:func:`predict_update_reference` compiled (:mod:`._filter_compiled`; each track steps
    alone, in scalars and 4 x 4 blocks)."""
    # by its module, not the package: the package imports this module
    from ._filter_compiled import predict_update_kernel as compiled_step

    means, covs, probabilities, times, streak, noise_var, stated_var, offset, wild = compiled_step(
        bank.means,
        bank.covariances,
        bank.model_probabilities,
        bank.times_s,
        bank.wild,
        bank.noise_var,
        bank.stated_var,
        bank.offset,
        np.ascontiguousarray(positions, dtype=np.float64),
        np.ascontiguousarray(covariances, dtype=np.float64),
        float(time_s),
        learn,
        np.ascontiguousarray(
            np.broadcast_to(
                settings.gate_chi2 if inflate_chi2 is None else inflate_chi2,
                bank.times_s.shape,
            ),
            dtype=np.float64,
        ),
        (
            settings.walking_accel_sd_mps2,
            settings.standing_drift_mps,
            settings.start_speed_sd_mps,
            settings.mean_dwell_s,
            settings.max_speed_mps,
            settings.gate_chi2,
            settings.min_measurement_sd_m,
            settings.steady_fix_probability,
            settings.noise_memory_s,
            settings.start_run_sd,
            settings.start_run_ratio,
        ),
    )
    updated = TrackBank(
        means=means,
        covariances=covs,
        model_probabilities=probabilities,
        times_s=times,
        wild=streak,
        noise_var=noise_var,
        stated_var=stated_var,
        offset=offset,
    )
    return updated, wild
