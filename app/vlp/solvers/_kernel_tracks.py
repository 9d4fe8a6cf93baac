"""Example arguments of the kernel table's tracking-filter row (:mod:`._kernel_table`): one
step of a room's tracks, :func:`app.vlp.tracking.step.predict_update_kernel`'s arguments.

Two tracks just started (a tracker's first step after a start), and a bank of random tracks
that reaches every branch of the step: levels not learned yet (NaN), tracks newer than the
fix (no step back in time), wild fixes (inflated, and the ones that end a streak of them),
and runs of far fixes that set a standing track off. Each with learning on and off, and the
inflation at the gate (None) or per fix, as a labelled and an anonymous step pass them.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..tracking.bank import N_MODELS, TrackBank
from ..tracking.filter import start_tracks
from ..tracking.settings import TrackerSettings
from ..typing import BoolArray

__all__ = ["predict_update_examples", "predict_update_parts"]

Arguments = tuple[Any, ...]
# The time of every example step (s): after some of the random tracks' times, before others.
_STEP_TIME_S = 0.9


def _random_bank(rng: np.random.Generator, n: int) -> TrackBank:
    """``n`` random tracks at times in [0, 1) s; every third has no learned noise level yet,
    every fourth no stated level, every fifth an offset of 4 sds per axis (a run's start)."""
    roots = rng.normal(0.0, 0.2, (n, N_MODELS, 4, 4))
    noise_var = rng.uniform(1e-4, 1e-2, n)
    noise_var[::3] = np.nan
    stated_var = rng.uniform(1e-4, 1e-2, n)
    stated_var[::4] = np.nan
    offset = rng.normal(0.0, 2.0, (n, 2))
    offset[::5] = 4.0
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
        offset=offset,
    )


def _random_fixes(rng: np.random.Generator, bank: TrackBank) -> tuple[np.ndarray, np.ndarray]:
    """Fixes ``(n, 2)`` and their covariances ``(n, 2, 2)`` for ``bank``'s tracks: most near
    the standing model, every fifth 1-3 m away per axis (wild, and along the offset
    :func:`_random_bank` gave those tracks)."""
    n = bank.size
    fixes = bank.means[:, 0, :2] + rng.normal(0.0, 0.1, (n, 2))
    fixes[::5] += rng.uniform(1.0, 3.0, (fixes[::5].shape[0], 2))
    roots = rng.normal(0.0, 0.05, (n, 2, 2))
    return fixes, roots @ np.swapaxes(roots, -1, -2) + 1e-4 * np.eye(2)


def predict_update_examples() -> list[Arguments]:
    """Two started tracks and 60 random ones, each learning or not, inflated at the gate or
    per fix (between the anonymous bound and the gate)."""
    settings = TrackerSettings()
    examples: list[Arguments] = []
    for learn in (True, False):
        for per_fix in (False, True):
            rng = np.random.default_rng(11)
            positions = np.array([[1.0, 1.0], [2.0, 2.0]])
            covariances = np.tile(1e-4 * np.eye(2), (2, 1, 1))
            started = start_tracks(positions, covariances, np.zeros(2), settings)
            moved = positions + np.array([[0.05, -0.02], [1.5, 1.0]])
            bank = _random_bank(rng, 60)
            fixes, noise = _random_fixes(rng, bank)
            for tracks, at, fix_covariances in (
                (started, moved, covariances),
                (bank, fixes, noise),
            ):
                inflate = (
                    rng.uniform(settings.anonymous_inflate_chi2, settings.gate_chi2, tracks.size)
                    if per_fix
                    else None
                )
                examples.append(
                    (tracks, at, fix_covariances, _STEP_TIME_S, settings, learn, inflate)
                )
    return examples


def predict_update_parts(answer: tuple[TrackBank, BoolArray]) -> tuple[Any, ...]:
    """The updated bank's arrays, field by field, and which fixes were wild."""
    bank, wild = answer
    return (*(getattr(bank, field.name) for field in dataclasses.fields(bank)), wild)
