"""How people move indoors, and how long a track lives: the tracker's one set of settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from ..errors import VLPError

__all__ = ["TrackerSettings"]


@dataclass(frozen=True)
class TrackerSettings:
    """Motion limits, gates and timeouts of a room's tracks (defaults: people walking).

    Attributes
    ----------
    walking_accel_sd_mps2 : float
        Sd of the white-noise acceleration of the walking (constant-velocity) model, m/s^2.
    standing_drift_mps : float
        Sd of the random walk of a standing terminal's position per square-root second
        (a hand that sways), m/s^0.5.
    start_speed_sd_mps : float
        Sd of the velocity a standing terminal may set off with, m/s (the standing model's
        velocity spread: what the walking model inherits when a terminal starts to walk).
    mean_dwell_s : float
        Mean time a terminal stays standing or walking before switching, seconds (the
        switching rate of the two-model mixture).
    max_speed_mps : float
        Fastest a terminal moves, m/s: a new track's speed prior (sd half of it) and the
        cap on a track's speed.
    gate_probability : float
        A fix whose innovation lies beyond this probability of the predicted spread is
        "wild": its covariance is inflated until it lies on the gate (not dropped), and an
        anonymous fix beyond it is not associated with the track.
    anonymous_inflate_probability : float
        A doubtful anonymous fix (see ``anonymous_doubt_ratio``) whose innovation lies beyond
        this probability of the predicted spread has its covariance inflated until it lies
        there (it still counts as wild only beyond ``gate_probability``). Lower than the
        gate: a shadowed terminal throws every estimate of an aggregated solve off, often by
        more than their covariances say, and one such estimate that pulls a track towards
        another walker swaps their identities.
    anonymous_doubt_ratio : float
        An anonymous fix is doubtful where another track explains it within this factor of
        the likelihood under the track it was assigned to (elsewhere a wrong estimate can pull
        its track away, but not onto another walker's, and the fix is inflated only beyond
        the gate, as a labelled one).
    rival_decision_ratio : float
        After a solve whose fixes two confirmed anonymous tracks could have taken either way
        round (within ``anonymous_doubt_ratio``), both ways are followed; the pair takes the
        other way once the later fixes make it this many times likelier than the kept one,
        and forgets it once the kept one is.
    rival_memory_solves : int
        How many solves both ways are followed at most (the kept one stays).
    reset_after_wild : int
        This many wild fixes in a row restart the track at the newest fix (a track cannot
        lock out a terminal that really moved).
    min_measurement_sd_m : float
        Floor on the sd of a fix in each axis, metres (a solver's covariance is never
        trusted below it).
    confirm_after_updates : int
        A tentative track is confirmed after this many updates.
    tentative_max_misses : int
        An anonymous tentative track missed by this many solves in a row is dropped.
    lost_after_misses : int
        An anonymous confirmed track missed by this many solves in a row is lost (a solve
        gives as many estimates as it was told targets: a track none of them claims twice
        running is most often one a wild estimate has left behind, and counting it would show
        a terminal twice; a lost track is claimed again, by a fix the confirmed and the
        tentative tracks leave).
    lost_after_s : float
        A track not updated for this long is ``lost``, seconds.
    drop_after_s : float
        A lost track is removed after this long without an update, seconds.
    history_s : float
        How long a track's points and the room's stream events are kept, seconds.
    standing_prior : float
        Probability that a new track stands (the rest: walks).
    steady_fix_probability : float
        Probability that a labelled fix which states the track's usual spread has the
        terminal's usual noise (the track's learned level) as its error rather than one as
        wide as its stated covariance (a fix that states k times the usual sd has 1/k of
        these odds: :func:`.filter.steady_probabilities`).
    noise_memory_s : float
        How long the learned noise level remembers, seconds (the time a terminal takes to
        walk into another part of the room, where the LEDs it sees differ).
    start_run_sd : float
        Two fixes in a row this many sds (of the track's learned fix-to-fix noise) away from
        a standing track, the second along the first, are a consistent run: the terminal has
        set off (a wild fix seldom repeats in the same direction).
    start_run_ratio : float
        How many times likelier a consistent run is from a walking terminal than from a
        standing one: the odds of walking are multiplied by it after a fix that ends one.
    """

    walking_accel_sd_mps2: float = 1.5
    standing_drift_mps: float = 0.01
    start_speed_sd_mps: float = 0.5
    mean_dwell_s: float = 2.0
    max_speed_mps: float = 3.0
    gate_probability: float = 0.999
    anonymous_inflate_probability: float = 0.55
    anonymous_doubt_ratio: float = 150.0
    rival_decision_ratio: float = 3.0
    rival_memory_solves: int = 5
    reset_after_wild: int = 3
    min_measurement_sd_m: float = 0.005
    confirm_after_updates: int = 3
    tentative_max_misses: int = 3
    lost_after_misses: int = 2
    lost_after_s: float = 5.0
    drop_after_s: float = 60.0
    history_s: float = 300.0
    standing_prior: float = 0.5
    steady_fix_probability: float = 0.95
    noise_memory_s: float = 2.0
    start_run_sd: float = 2.0
    start_run_ratio: float = 100.0

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not (math.isfinite(value) and value > 0):
                raise VLPError(
                    f"{item.name} must be a finite number > 0, got {value!r}", field=item.name
                )
        if not self.standing_prior < 1.0:
            raise VLPError(
                f"standing_prior must be below 1, got {self.standing_prior!r}",
                field="standing_prior",
            )
        if not self.steady_fix_probability < 1.0:
            raise VLPError(
                f"steady_fix_probability must be below 1, got {self.steady_fix_probability!r}",
                field="steady_fix_probability",
            )
        if not self.gate_probability < 1.0:
            raise VLPError(
                f"gate_probability must be below 1, got {self.gate_probability!r}",
                field="gate_probability",
            )
        if not self.anonymous_inflate_probability < 1.0:
            raise VLPError(
                "anonymous_inflate_probability must be below 1, got "
                f"{self.anonymous_inflate_probability!r}",
                field="anonymous_inflate_probability",
            )
        if not self.rival_decision_ratio > 1.0:
            raise VLPError(
                f"rival_decision_ratio must be above 1, got {self.rival_decision_ratio!r}",
                field="rival_decision_ratio",
            )
        if self.drop_after_s < self.lost_after_s:
            raise VLPError(
                f"drop_after_s ({self.drop_after_s:g}) must be at least lost_after_s "
                f"({self.lost_after_s:g})",
                field="drop_after_s",
            )

    @property
    def gate_chi2(self) -> float:
        """The gate on the squared Mahalanobis distance of a 2-D innovation:
        ``-2 ln(1 - gate_probability)`` (the chi-square quantile with 2 degrees of freedom)."""
        return -2.0 * math.log1p(-self.gate_probability)

    @property
    def anonymous_inflate_chi2(self) -> float:
        """The squared Mahalanobis distance an anonymous fix beyond it is inflated to:
        ``-2 ln(1 - anonymous_inflate_probability)``."""
        return -2.0 * math.log1p(-self.anonymous_inflate_probability)

    @property
    def anonymous_doubt_margin(self) -> float:
        """``anonymous_doubt_ratio`` as a difference of association costs (twice the negative
        log-likelihood): ``2 ln(anonymous_doubt_ratio)``."""
        return 2.0 * math.log(self.anonymous_doubt_ratio)
