"""The filter state of a room's tracks: one batch of arrays, never an object per track."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..typing import BoolArray, FloatArray, IntArray

__all__ = ["N_MODELS", "TrackBank"]

N_MODELS = 2  # 0: standing, 1: walking


@dataclass(frozen=True)
class TrackBank:
    """The filter state of ``n`` tracks.

    Attributes
    ----------
    means : ndarray of shape (n, 2, 4)
        Each model's state ``[x, y, vx, vy]`` per track (m, m/s).
    covariances : ndarray of shape (n, 2, 4, 4)
        Each model's state covariance.
    model_probabilities : ndarray of shape (n, 2)
        Probability of standing and of walking.
    times_s : ndarray of shape (n,)
        Time of the state, seconds (any fixed origin, e.g. POSIX time).
    wild : ndarray of shape (n,), int
        Wild fixes in a row.
    noise_var : ndarray of shape (n,), m^2
        The track's learned variance (per axis) of the part of a fix's error that changes
        from fix to fix: a fix is trusted down to it whatever its stated covariance says
        (NaN: not learned yet, the next fix's stated covariance starts it).
    stated_var : ndarray of shape (n,), m^2
        The harmonic mean (same memory) of the fixes' stated variances per axis: what the
        solver says a fix's whole error is, weighted as a filter weighs the fixes. Where it
        exceeds ``noise_var`` the rest is error successive fixes share, which no filter
        averages away (:func:`.filter.estimates`).
    offset : ndarray of shape (n, 2)
        The last fix's offset from the standing model, in sds of a standing terminal's fix
        (:func:`.starts.whitened_offsets`; zeros: none, or a fix that may have been another
        terminal's): where a run of fixes that tells a start begins.
    """

    means: FloatArray
    covariances: FloatArray
    model_probabilities: FloatArray
    times_s: FloatArray
    wild: IntArray
    noise_var: FloatArray
    stated_var: FloatArray
    offset: FloatArray

    @property
    def size(self) -> int:
        """The number of tracks ``n``."""
        return int(self.times_s.shape[0])

    def take(self, rows: IntArray | BoolArray) -> TrackBank:
        """The tracks at ``rows`` (indices or a mask)."""
        return TrackBank(
            means=self.means[rows],
            covariances=self.covariances[rows],
            model_probabilities=self.model_probabilities[rows],
            times_s=self.times_s[rows],
            wild=self.wild[rows],
            noise_var=self.noise_var[rows],
            stated_var=self.stated_var[rows],
            offset=self.offset[rows],
        )

    def put(self, rows: IntArray | BoolArray, other: TrackBank) -> TrackBank:
        """A copy with the tracks at ``rows`` replaced by ``other``'s, in order."""
        out = TrackBank(
            means=self.means.copy(),
            covariances=self.covariances.copy(),
            model_probabilities=self.model_probabilities.copy(),
            times_s=self.times_s.copy(),
            wild=self.wild.copy(),
            noise_var=self.noise_var.copy(),
            stated_var=self.stated_var.copy(),
            offset=self.offset.copy(),
        )
        out.means[rows] = other.means
        out.covariances[rows] = other.covariances
        out.model_probabilities[rows] = other.model_probabilities
        out.times_s[rows] = other.times_s
        out.wild[rows] = other.wild
        out.noise_var[rows] = other.noise_var
        out.stated_var[rows] = other.stated_var
        out.offset[rows] = other.offset
        return out

    @staticmethod
    def concatenate(first: TrackBank, second: TrackBank) -> TrackBank:
        """``first``'s tracks followed by ``second``'s."""
        return TrackBank(
            means=np.concatenate((first.means, second.means)),
            covariances=np.concatenate((first.covariances, second.covariances)),
            model_probabilities=np.concatenate(
                (first.model_probabilities, second.model_probabilities)
            ),
            times_s=np.concatenate((first.times_s, second.times_s)),
            wild=np.concatenate((first.wild, second.wild)),
            noise_var=np.concatenate((first.noise_var, second.noise_var)),
            stated_var=np.concatenate((first.stated_var, second.stated_var)),
            offset=np.concatenate((first.offset, second.offset)),
        )

    @staticmethod
    def empty() -> TrackBank:
        """No track."""
        return TrackBank(
            means=np.zeros((0, N_MODELS, 4)),
            covariances=np.zeros((0, N_MODELS, 4, 4)),
            model_probabilities=np.zeros((0, N_MODELS)),
            times_s=np.zeros(0),
            wild=np.zeros(0, dtype=np.intp),
            noise_var=np.zeros(0),
            stated_var=np.zeros(0),
            offset=np.zeros((0, 2)),
        )
