"""Tracks' lives: association of anonymous fixes, labelled updates, confirmation and loss.

A room's tracks are one :class:`Tracks` batch. A labelled fix (its terminal is known) updates
its terminal's track; anonymous fixes (aggregated measurements say where targets are, not
who) are associated with the anonymous tracks by gated assignment of least total cost
(the negative log-likelihood of the fix under the track's two models, each with its
Mahalanobis distance and the log-determinant of its innovation covariance,
:func:`scipy.optimize.linear_sum_assignment`), confirmed tracks first, then tentative ones,
then lost ones. A fix no track claims starts a tentative
track; tentative tracks are confirmed after ``confirm_after_updates`` updates and dropped
after ``tentative_max_misses`` missed solves; a track not updated for ``lost_after_s`` is
lost, and removed after ``drop_after_s``. Which ids the tracks carry is the caller's
business: rows here are positions in the batch.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..typing import BoolArray, FloatArray, IntArray
from .association import INFEASIBLE, assigned, associate, costs
from .filter import TrackBank, combined, predict, start_tracks
from .rivals import Rivals, follow_both_ways
from .settings import TrackerSettings
from .step import predict_update

__all__ = [
    "CONFIRMED",
    "LOST",
    "STATUS_NAMES",
    "TENTATIVE",
    "Rivals",
    "Step",
    "Tracks",
    "age_tracks",
    "associate",
    "joined",
    "step_anonymous",
    "step_labelled",
]

TENTATIVE, CONFIRMED, LOST = 0, 1, 2
STATUS_NAMES = ("tentative", "confirmed", "lost")

# Added to an anonymous track's assignment costs per step down from confirmed (tentative:
# one, lost: two). An allowed pair costs far less (a few metres squared over the floor on a
# fix's variance, ~1e6 at most), so the assignment first gives as many fixes as it can to
# confirmed tracks; far below INFEASIBLE, which it still tells apart.
TIER_COST = 1e9


@dataclass(frozen=True)
class Tracks:
    """A room's tracks: filter state and lifecycle.

    Attributes
    ----------
    bank : TrackBank
        Filter state of the ``n`` tracks (``bank.times_s``: time of the last update).
    status : ndarray of shape (n,), int
        :data:`TENTATIVE`, :data:`CONFIRMED` or :data:`LOST`.
    updates : ndarray of shape (n,), int
        Fixes that moved the track.
    misses : ndarray of shape (n,), int
        Anonymous solves in a row that did not claim the track.
    rivals : Rivals or None, default=None
        Pairs of anonymous tracks followed both ways after an ambiguous solve (None: no pair).
    """

    bank: TrackBank
    status: IntArray
    updates: IntArray
    misses: IntArray
    rivals: Rivals | None = None

    @property
    def size(self) -> int:
        """The number of tracks ``n``."""
        return self.bank.size

    @staticmethod
    def empty() -> Tracks:
        """No track."""
        zeros = np.zeros(0, dtype=np.intp)
        return Tracks(bank=TrackBank.empty(), status=zeros, updates=zeros, misses=zeros)

    def take(self, rows: IntArray | BoolArray) -> Tracks:
        """The tracks at ``rows`` (indices or a mask), in that order."""
        return Tracks(
            bank=self.bank.take(rows),
            status=self.status[rows],
            updates=self.updates[rows],
            misses=self.misses[rows],
            rivals=None if self.rivals is None else self.rivals.take(rows),
        )

    def put(self, rows: IntArray, other: Tracks) -> Tracks:
        """A copy with the tracks at ``rows`` replaced by ``other``'s, in order."""
        status, updates, misses = self.status.copy(), self.updates.copy(), self.misses.copy()
        status[rows], updates[rows], misses[rows] = other.status, other.updates, other.misses
        rivals = None
        if self.rivals is not None or other.rivals is not None:
            rivals = _rivals_of(self).put(rows, _rivals_of(other))
        return Tracks(self.bank.put(rows, other.bank), status, updates, misses, rivals)


def _rivals_of(tracks: Tracks) -> Rivals:
    return Rivals.none(tracks.bank) if tracks.rivals is None else tracks.rivals


@dataclass(frozen=True)
class Step:
    """What one set of fixes did.

    Attributes
    ----------
    tracks : Tracks
        The tracks afterwards: the old ones in their rows, new ones appended.
    fix_rows : ndarray of shape (m,), int
        The track (row of ``tracks``) each fix went to.
    moved : ndarray of shape (m,), bool
        Whether the fix moved its track (False for a fix older than its track's state).
    wild : ndarray of shape (m,), bool
        Whether the fix lay beyond the gate (its covariance was inflated).
    """

    tracks: Tracks
    fix_rows: IntArray
    moved: BoolArray
    wild: BoolArray


def _apply(
    tracks: Tracks,
    rows: IntArray,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
    learn: bool,
    inflate_chi2: FloatArray | None = None,
) -> tuple[Tracks, BoolArray, BoolArray]:
    """Predict and update the tracks at ``rows`` with their fixes (in order); a fix older than
    its track's state does not move it. Returns the tracks, ``moved`` and ``wild`` per fix."""
    moved = tracks.bank.times_s[rows] <= time_s
    wild = np.zeros(rows.shape[0], dtype=bool)
    if not np.any(moved):
        return tracks, moved, wild
    live = rows[moved]
    # Every track, in its order (a labelled room's usual step): no copy in and out.
    whole = live.shape[0] == tracks.size and bool(np.all(live == np.arange(tracks.size)))
    chosen = tracks.bank if whole else tracks.bank.take(live)
    if not np.all(moved):
        positions, covariances = positions[moved], covariances[moved]
        inflate_chi2 = None if inflate_chi2 is None else inflate_chi2[moved]
    result = predict_update(
        chosen, positions, covariances, time_s, settings, learn=learn, inflate_chi2=inflate_chi2
    )
    wild[moved] = result.wild
    updates = tracks.updates.copy()
    updates[live] += 1
    status = tracks.status.copy()
    confirmed = updates[live] >= settings.confirm_after_updates
    status[live] = np.where(confirmed | (status[live] != TENTATIVE), CONFIRMED, TENTATIVE)
    misses = tracks.misses.copy()
    misses[live] = 0
    bank = result.bank if whole else tracks.bank.put(live, result.bank)
    after = Tracks(bank=bank, status=status, updates=updates, misses=misses, rivals=tracks.rivals)
    return after, moved, wild


def _started(
    positions: FloatArray, covariances: FloatArray, time_s: float, settings: TrackerSettings
) -> Tracks:
    count = positions.shape[0]
    bank = start_tracks(positions, covariances, np.full(count, time_s), settings)
    ones = np.ones(count, dtype=np.intp)
    status = np.where(ones >= settings.confirm_after_updates, CONFIRMED, TENTATIVE)
    return Tracks(
        bank=bank,
        status=status.astype(np.intp),
        updates=ones,
        misses=np.zeros(count, dtype=np.intp),
    )


def joined(first: Tracks, second: Tracks) -> Tracks:
    """``first``'s tracks followed by ``second``'s (whose pairs, if any, are their own)."""
    rivals = None
    if first.rivals is not None or second.rivals is not None:
        rivals = Rivals.concatenate(_rivals_of(first), _rivals_of(second))
    return Tracks(
        bank=TrackBank.concatenate(first.bank, second.bank),
        status=np.concatenate((first.status, second.status)),
        updates=np.concatenate((first.updates, second.updates)),
        misses=np.concatenate((first.misses, second.misses)),
        rivals=rivals,
    )


def step_labelled(
    tracks: Tracks,
    rows: IntArray,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
    *,
    learn: bool = True,
    inflate_chi2: FloatArray | None = None,
) -> Step:
    """Fixes whose terminals are known: fix ``k`` updates track ``rows[k]``, or starts a new
    track where ``rows[k]`` is -1.

    Parameters
    ----------
    tracks : Tracks
    rows : ndarray of shape (m,), int
        Distinct rows of ``tracks``, or -1.
    positions : ndarray of shape (m, 2), metres
    covariances : ndarray of shape (m, 2, 2), m^2
    time_s : float
        The fixes' time, seconds.
    settings : TrackerSettings
    learn : bool, default=True
        Whether the tracks learn their fixes' noise level (:func:`.filter.update`).

    Returns
    -------
    Step
    """
    old = rows >= 0
    updated, moved_old, wild_old = _apply(
        tracks,
        rows[old],
        positions[old],
        covariances[old],
        time_s,
        settings,
        learn,
        None if inflate_chi2 is None else inflate_chi2[old],
    )
    fix_rows = rows.copy()
    moved = np.ones(rows.shape[0], dtype=bool)
    moved[old] = moved_old
    wild = np.zeros(rows.shape[0], dtype=bool)
    wild[old] = wild_old
    if np.all(old):  # no new track: nothing to append
        return Step(tracks=updated, fix_rows=fix_rows, moved=moved, wild=wild)
    new = _started(positions[~old], covariances[~old], time_s, settings)
    fix_rows[~old] = tracks.size + np.arange(new.size)
    return Step(tracks=joined(updated, new), fix_rows=fix_rows, moved=moved, wild=wild)


def step_anonymous(
    tracks: Tracks,
    positions: FloatArray,
    covariances: FloatArray,
    time_s: float,
    settings: TrackerSettings,
) -> Step:
    """Anonymous fixes of one solve: associated with ``tracks`` (all anonymous), the rest
    start tentative tracks; tracks no fix claimed count a miss. Confirmed tracks claim
    first, tentative ones the fixes left, lost ones the rest: a lost track, whose spread has
    grown while it was missed, would otherwise explain a wrong fix better than the confirmed
    track it belongs to, and take that terminal's next fixes and its identity. A fix that
    another track explains within ``anonymous_doubt_ratio`` of its own is inflated beyond
    ``anonymous_inflate_probability`` of its track's spread, not only beyond the gate.

    Parameters
    ----------
    tracks : Tracks
        The room's anonymous tracks (lost ones may be claimed again).
    positions : ndarray of shape (m, 2), metres
    covariances : ndarray of shape (m, 2, 2), m^2
    time_s : float
        The solve's time, seconds.
    settings : TrackerSettings

    Returns
    -------
    Step
        Confirmed tracks missed ``lost_after_misses`` times in a row are lost. Tentative
        tracks missed ``tentative_max_misses`` times are still in ``tracks`` with
        their misses counted: :func:`age_tracks` tells the caller to remove them.
    """
    predicted = predict(tracks.bank, np.full(tracks.size, time_s), settings)
    elapsed = np.maximum(time_s - tracks.bank.times_s, 0.0)
    rows = np.full(positions.shape[0], -1, dtype=np.intp)
    inflate = np.full(positions.shape[0], settings.gate_chi2)
    cost = None
    if tracks.size and positions.shape[0]:
        cost = costs(predicted, positions, covariances, settings, elapsed)
        # Doubt (below) is still weighed on the likelihoods alone.
        track_rows, fix_cols = assigned(cost + _claim_order(tracks.status)[:, None])
        rows[fix_cols] = track_rows
        # A fix another track explains almost as well is doubtful: if it is wrong (one
        # shadowed terminal throws a whole aggregated solve off, often by more than its
        # covariances say), pulling its track towards that other walker swaps their
        # identities. Beyond the anonymous bound it moves its track only as a fix on the
        # bound would.
        others = cost.copy()
        others[track_rows, fix_cols] = np.inf
        second = np.min(others[:, fix_cols], axis=0)
        doubtful = second - cost[track_rows, fix_cols] < settings.anonymous_doubt_margin
        inflate[fix_cols[doubtful]] = settings.anonymous_inflate_chi2
    # A fix of an aggregated solve may be another terminal's: its track does not learn a
    # noise level from it.
    step = step_labelled(
        tracks,
        rows,
        positions,
        covariances,
        time_s,
        settings,
        learn=False,
        inflate_chi2=inflate,
    )
    claimed = np.zeros(step.tracks.size, dtype=bool)
    claimed[step.fix_rows] = True
    misses = np.where(claimed, step.tracks.misses, step.tracks.misses + 1)
    # A confirmed track no solve claims for several solves in a row is lost (it may be
    # claimed again); its place in the answer goes to whatever the solves now see.
    status = np.where(
        (step.tracks.status == CONFIRMED) & (misses >= settings.lost_after_misses),
        LOST,
        step.tracks.status,
    )
    after = Tracks(
        bank=step.tracks.bank,
        status=status.astype(np.intp),
        updates=step.tracks.updates,
        misses=misses.astype(np.intp),
        rivals=step.tracks.rivals,
    )
    fix_rows = step.fix_rows
    if cost is not None:
        bank, rivals, fix_rows = follow_both_ways(
            _rivals_of(after),
            after.bank,
            fix_rows,
            tracks.bank,
            tracks.status == CONFIRMED,
            cost,
            positions,
            covariances,
            time_s,
            settings,
        )
        after = replace(after, bank=bank, rivals=rivals)
    was_tentative = np.concatenate(
        (tracks.status == TENTATIVE, np.ones(after.size - tracks.size, dtype=bool))
    )
    after, moved_to = _in_lost_places(after, was_tentative, time_s, settings)
    return Step(tracks=after, fix_rows=moved_to[fix_rows], moved=step.moved, wild=step.wild)


def _claim_order(status: IntArray) -> FloatArray:
    """What each track adds to its assignment costs ``(n,)``: confirmed tracks claim a
    solve's fixes first, tentative ones the fixes left, lost ones the rest."""
    tiers = np.select([status == TENTATIVE, status == LOST], [1.0, 2.0], 0.0)
    return np.asarray(TIER_COST * tiers, dtype=np.float64)


def _in_lost_places(
    tracks: Tracks, was_tentative: BoolArray, time_s: float, settings: TrackerSettings
) -> tuple[Tracks, IntArray]:
    """Tracks confirmed by this solve that take the places of tracks it missed.

    A wild fix can pull a track away from its terminal; the terminal's next fixes then start
    a tentative track while the old one coasts, and the terminal's id would change when the
    new one is confirmed. A track just confirmed instead continues a confirmed or lost track
    that no solve claimed since it started (misses at least its updates), from which it lies
    within reach (``max_speed_mps`` times the time since that track's last update, plus the
    95 % spread of both positions); pairs of least total distance. The coasting track's row
    takes the new state (so keeps its id), and the new track's row is left tentative and
    missed out, for :func:`age_tracks` to remove.

    Returns
    -------
    tracks : Tracks
    moved_to : ndarray of shape (n,), int
        The row that now holds each row's track.
    """
    moved_to = np.arange(tracks.size)
    fresh = np.nonzero(was_tentative & (tracks.status == CONFIRMED))[0]
    coasting = np.nonzero(~was_tentative & (tracks.status != TENTATIVE) & (tracks.misses > 0))[0]
    if fresh.size == 0 or coasting.size == 0:
        return tracks, moved_to
    mean, covariance = combined(tracks.bank)
    gap = np.linalg.norm(mean[fresh, None, :2] - mean[None, coasting, :2], axis=2)
    position_var = np.trace(covariance[:, :2, :2], axis1=1, axis2=2)
    spread = 2.448 * np.sqrt(position_var[fresh, None] + position_var[None, coasting])
    idle = np.maximum(time_s - tracks.bank.times_s[coasting], 0.0)
    allowed = gap <= settings.max_speed_mps * idle[None, :] + spread
    allowed &= tracks.misses[None, coasting] >= tracks.updates[fresh, None]
    if not np.any(allowed):
        return tracks, moved_to
    rows, cols = linear_sum_assignment(np.where(allowed, gap, INFEASIBLE))
    keep = allowed[rows, cols]
    new, old = fresh[rows[keep]], coasting[cols[keep]]
    status, updates, misses = tracks.status.copy(), tracks.updates.copy(), tracks.misses.copy()
    status[old], updates[old], misses[old] = CONFIRMED, updates[old] + updates[new], 0
    status[new], misses[new] = TENTATIVE, settings.tentative_max_misses
    moved_to[new] = old
    bank = tracks.bank.put(old, tracks.bank.take(new))
    rivals = tracks.rivals
    if rivals is not None:  # a row that takes another's state ends its pair
        pair = rivals.pair.copy()
        pair[old] = pair[new] = 0
        rivals = replace(rivals, pair=pair).paired()
    after = Tracks(bank=bank, status=status, updates=updates, misses=misses, rivals=rivals)
    return after, moved_to


def age_tracks(
    tracks: Tracks, now_s: float, settings: TrackerSettings
) -> tuple[IntArray, BoolArray]:
    """Statuses at ``now_s`` and which tracks end.

    A track not updated for ``lost_after_s`` is lost; one not updated for ``drop_after_s``
    ends, as does a tentative track missed ``tentative_max_misses`` times in a row.

    Returns
    -------
    status : ndarray of shape (n,), int
    removed : ndarray of shape (n,), bool
    """
    idle = now_s - tracks.bank.times_s
    status = np.where(idle > settings.lost_after_s, LOST, tracks.status).astype(np.intp)
    removed = (idle > settings.drop_after_s) | (
        (tracks.status == TENTATIVE) & (tracks.misses >= settings.tentative_max_misses)
    )
    return status, removed
