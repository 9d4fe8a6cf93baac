"""Starts: a standing terminal that sets off, told from a wild fix by a consistent run.

One fix far from a standing track is as likely a wild fix (a shadowed LED) as the first step
of a walk, and the standing model's wide-fix hypothesis takes most of it: the track lags the
walker by most of the fix's offset. A next fix that lies further out along the same direction
is what a walker gives (it draws away from where it stood) and a wild fix seldom does (an
independent one points anywhere; one that repeats, a hand that stays on an LED, lands where
the last one did). Each track keeps its last fix's offset from the standing model, in sds of
a standing terminal's fix (the fix-to-fix noise the track has learned, not the fix's stated
covariance, which a start does not change); where a track that stood gets a fix further along
an offset of at least ``start_run_sd``, its odds of walking after the update are multiplied
by ``start_run_ratio``. The odds, not the switching probability: raising the probability of
a switch would also mix the standing model's state, which the first fix did not move, into
the walking model's, which it did.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..typing import BoolArray, FloatArray
from .bank import TrackBank
from .settings import TrackerSettings

__all__ = ["after_runs", "consistent_runs", "whitened_offsets"]


def whitened_offsets(
    means: FloatArray,
    covariances: FloatArray,
    noise_var: FloatArray,
    positions: FloatArray,
    fix_var: FloatArray,
    dt: FloatArray,
    settings: TrackerSettings,
) -> FloatArray:
    """Each fix's offset ``(n, 2)`` from its track's standing model, in sds.

    Parameters
    ----------
    means, covariances : ndarray of shape (n, 2, 4), (n, 2, 4, 4)
        The tracks' models before the step (:class:`.filter.TrackBank`).
    noise_var : ndarray of shape (n,), m^2
        The tracks' learned fix-to-fix variance per axis (NaN: the fix's ``fix_var``).
    positions : ndarray of shape (n, 2), metres
    fix_var : ndarray of shape (n,), m^2
        Each fix's stated variance per axis (floored).
    dt : ndarray of shape (n,), seconds
        Time since each track's state.
    settings : TrackerSettings

    Returns
    -------
    ndarray of shape (n, 2)
        The offset over the sd of a standing terminal's fix about the standing model's
        position: the learned noise, the position's spread and its drift over ``dt``.
    """
    level = np.where(np.isfinite(noise_var), noise_var, fix_var)
    spread = (covariances[:, 0, 0, 0] + covariances[:, 0, 1, 1]) / 2.0
    var = level + spread + settings.standing_drift_mps**2 * dt
    return np.asarray((positions - means[:, 0, :2]) / np.sqrt(var)[:, None])


def consistent_runs(
    previous: FloatArray, offsets: FloatArray, settings: TrackerSettings
) -> BoolArray:
    """Whether each fix lies further along its track's previous offset than that offset
    reached, which was at least ``start_run_sd`` (``(n, 2)`` each, in sds:
    :func:`whitened_offsets`): a walker draws away from where it stood, while a wild fix
    that repeats (a hand that stays on an LED) lands where the last one did."""
    norm = np.hypot(previous[:, 0], previous[:, 1])
    along = np.einsum("na,na->n", previous, offsets) / np.maximum(norm, 1e-12)
    return np.asarray((norm >= settings.start_run_sd) & (along >= norm))


def after_runs(
    updated: TrackBank,
    before: TrackBank,
    offsets: FloatArray,
    learn: bool,
    settings: TrackerSettings,
) -> TrackBank:
    """The updated tracks with the odds of walking multiplied by ``start_run_ratio`` where a
    track that stood (``before``: its state before the step) ends a consistent run, and this
    fix's offsets kept for the next (none where ``learn`` is False: a fix that may be another
    terminal's starts no run)."""
    if not learn:
        return dataclasses.replace(updated, offset=np.zeros_like(offsets))
    # Only a standing track sets off: a walking one's offsets from its standing model run on
    # with every step, and would pin it to walking when it stops.
    standing = before.model_probabilities[:, 0] >= 0.5
    run = standing & consistent_runs(before.offset, offsets, settings)
    walking = updated.model_probabilities[:, 1]
    odds = settings.start_run_ratio * walking
    total = 1.0 - walking + odds
    raised = np.maximum(np.stack(((1.0 - walking) / total, odds / total), axis=1), 1e-9)
    probabilities = np.where(run[:, None], raised, updated.model_probabilities)
    return dataclasses.replace(updated, model_probabilities=probabilities, offset=offsets.copy())
