"""Pairs of anonymous tracks followed both ways after an ambiguous solve.

Two walkers who pass close are where positions alone cannot tell them apart: the solve at
which their fixes could go either way round at nearly the same cost is often decided wrong,
and the next solves then follow the swap. Where they part, the next fixes tell the two ways
apart, but by then each track's state holds the swap. So the other way is followed too, for a
few solves, and taken if the later fixes favour it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..typing import BoolArray, FloatArray, IntArray
from .association import INFEASIBLE, costs
from .bank import TrackBank
from .filter import predict
from .settings import TrackerSettings
from .step import predict_update

__all__ = ["Rivals", "follow_both_ways"]


@dataclass(frozen=True)
class Rivals:
    """The other way an ambiguous solve could have gone, for pairs of anonymous tracks.

    Where two confirmed tracks' fixes of one solve could have been assigned the other way
    round at nearly the same cost, both ways are followed for a few solves and the one the
    later fixes favour is kept (:func:`step_anonymous`).

    Attributes
    ----------
    pair : ndarray of shape (n,), int
        A number the two tracks of a pair share, 0 for a track in none.
    bank : TrackBank
        Each track's filter state had the pair's fixes gone the other way since the ambiguous
        solve (meaningless where ``pair`` is 0).
    score : ndarray of shape (n,)
        The other way's total assignment cost since then minus the kept way's (twice the log
        of the likelihood ratio of the kept way over the other); the same on both tracks.
    solves : ndarray of shape (n,), int
        Solves since the ambiguous one.
    """

    pair: IntArray
    bank: TrackBank
    score: FloatArray
    solves: IntArray

    @staticmethod
    def none(bank: TrackBank) -> Rivals:
        """No pair, for the tracks of ``bank``."""
        count = bank.size
        return Rivals(
            pair=np.zeros(count, dtype=np.intp),
            bank=bank,
            score=np.zeros(count),
            solves=np.zeros(count, dtype=np.intp),
        )

    def take(self, rows: IntArray | BoolArray) -> Rivals:
        """The tracks at ``rows`` (indices or a mask); a pair that loses one track ends."""
        taken = Rivals(self.pair[rows], self.bank.take(rows), self.score[rows], self.solves[rows])
        return taken.paired()

    def paired(self) -> Rivals:
        """The same, with every number not shared by exactly two tracks reset to 0."""
        values, counts = np.unique(self.pair, return_counts=True)
        single = values[(counts != 2) & (values != 0)]
        if single.size == 0:
            return self
        return replace(self, pair=np.where(np.isin(self.pair, single), 0, self.pair))

    def put(self, rows: IntArray, other: Rivals) -> Rivals:
        """A copy with the tracks at ``rows`` replaced by ``other``'s, in order (a pair
        that loses one track ends)."""
        pair, score, solves = self.pair.copy(), self.score.copy(), self.solves.copy()
        pair[rows], score[rows], solves[rows] = other.pair, other.score, other.solves
        return Rivals(pair, self.bank.put(rows, other.bank), score, solves).paired()

    @staticmethod
    def concatenate(first: Rivals, second: Rivals) -> Rivals:
        """``first``'s tracks followed by ``second``'s, whose pairs are renumbered after
        ``first``'s."""
        shift = int(np.max(first.pair, initial=0))
        return Rivals(
            pair=np.concatenate((first.pair, np.where(second.pair > 0, second.pair + shift, 0))),
            bank=TrackBank.concatenate(first.bank, second.bank),
            score=np.concatenate((first.score, second.score)),
            solves=np.concatenate((first.solves, second.solves)),
        )


def follow_both_ways(
    rivals: Rivals,
    bank: TrackBank,
    fix_rows: IntArray,
    before: TrackBank,
    confirmed: BoolArray,
    cost: FloatArray,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
) -> tuple[TrackBank, Rivals | None, IntArray]:
    """The pairs after one anonymous solve, and what they change.

    Where two confirmed tracks' fixes of a solve could have been assigned the other way
    round within ``anonymous_doubt_ratio`` of the kept way's likelihood, the other way is
    followed too: each track's state had the pair's fixes been swapped, updated on every
    later solve with the two fixes the pair claims (paired whichever way fits it better),
    and the difference of the two ways' total assignment costs. Once the other way is
    likelier by ``rival_decision_ratio`` the pair takes its states (each track then
    continues the walker the later fixes say it was following); once the kept way is, after
    ``rival_memory_solves`` solves, or when either track misses a solve, the other way is
    forgotten.

    Parameters
    ----------
    rivals : Rivals
        The pairs before the solve, for the tracks after it (``n'`` rows; new tracks last).
    bank : TrackBank
        The ``n'`` tracks updated with the solve's fixes as assigned.
    fix_rows : ndarray of shape (m,), int
        The row each fix went to.
    before : TrackBank
        The ``n`` tracks before the solve (the first ``n`` rows of ``bank``).
    confirmed : ndarray of shape (n,), bool
        Which of them were confirmed (only those pair).
    cost : ndarray of shape (n, m)
        The solve's assignment costs (:func:`.association.costs`).
    positions : ndarray of shape (m, 2), metres
    covariances : ndarray of shape (m, 2, 2), m^2
    time_s : float
    settings : TrackerSettings

    Returns
    -------
    bank : TrackBank
        The tracks, with the states of the pairs that took the other way.
    rivals : Rivals or None
        The pairs after the solve (None: none).
    fix_rows : ndarray of shape (m,), int
        The row each fix went to, the other way where a pair took it.
    """
    count = before.size
    pair, score, solves = rivals.pair.copy(), rivals.score.copy(), rivals.solves.copy()
    rival_bank = rivals.bank
    fix_rows = fix_rows.copy()
    fix_of = np.full(bank.size, -1, dtype=np.intp)
    fix_of[fix_rows] = np.arange(fix_rows.shape[0])
    decision = 2.0 * math.log(settings.rival_decision_ratio)
    settled = np.zeros(count, dtype=bool)  # took the other way at this solve
    for key in np.unique(pair[:count][pair[:count] > 0]):
        two = np.nonzero(pair[:count] == key)[0]
        pair[two] = 0
        if two.size != 2 or np.any(fix_of[two] < 0):
            continue
        fixes = fix_of[two]
        other = rival_bank.take(two)
        both = costs(
            predict(other, np.full(2, time_s), settings),
            positions[fixes],
            covariances[fixes],
            settings,
            np.maximum(time_s - other.times_s, 0.0),
        )
        straight, crossed = both[0, 0] + both[1, 1], both[0, 1] + both[1, 0]
        order = fixes if straight <= crossed else fixes[::-1]
        kept = cost[two[0], fixes[0]] + cost[two[1], fixes[1]]
        total = float(score[two[0]] + min(straight, crossed) - kept)
        if not total < INFEASIBLE / 2:
            continue
        moved = _updated(other, positions[order], covariances[order], time_s, settings)
        if total < -decision:
            bank = bank.put(two, moved)
            fix_rows[order] = two
            settled[two] = True
        elif total <= decision and solves[two[0]] + 1 < settings.rival_memory_solves:
            pair[two], score[two], solves[two] = key, total, solves[two] + 1
            rival_bank = rival_bank.put(two, moved)
    # New pairs: confirmed tracks that each claimed a fix of this solve, most ambiguous first.
    free = (fix_of[:count] >= 0) & confirmed & (pair[:count] == 0) & ~settled
    claimed = np.nonzero(free)[0]
    first, second = np.triu_indices(claimed.size, 1)
    rows_i, rows_j = claimed[first], claimed[second]
    fix_i, fix_j = fix_of[rows_i], fix_of[rows_j]
    margin = cost[rows_i, fix_j] + cost[rows_j, fix_i] - cost[rows_i, fix_i] - cost[rows_j, fix_j]
    for k in np.argsort(margin, kind="stable"):
        two = np.array([rows_i[k], rows_j[k]])
        if not margin[k] < settings.anonymous_doubt_margin or np.any(pair[two] > 0):
            continue
        swapped = np.array([fix_j[k], fix_i[k]])
        moved = _updated(
            before.take(two), positions[swapped], covariances[swapped], time_s, settings
        )
        rival_bank = rival_bank.put(two, moved)
        pair[two] = int(np.max(pair, initial=0)) + 1
        score[two], solves[two] = margin[k], 0
    if not np.any(pair > 0):
        return bank, None, fix_rows
    return bank, Rivals(pair=pair, bank=rival_bank, score=score, solves=solves), fix_rows


def _updated(
    bank: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
) -> TrackBank:
    """Two tracks of a pair updated with their fixes the other way, as doubtful anonymous
    fixes (inflated beyond ``anonymous_inflate_probability``, no noise level learned)."""
    inflate = np.full(bank.size, settings.anonymous_inflate_chi2)
    return predict_update(
        bank, positions, covariances, time_s, settings, learn=False, inflate_chi2=inflate
    ).bank
