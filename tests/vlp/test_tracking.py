"""The tracking core against independent computations: a textbook Kalman filter, the gate's
closed form, association, lifecycle, GOSPA."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose

from app.vlp.errors import VLPError
from app.vlp.tracking import (
    CONFIRMED,
    LOST,
    N_MODELS,
    TENTATIVE,
    TrackBank,
    TrackerSettings,
    Tracks,
    age_tracks,
    associate,
    combined,
    estimates,
    gospa,
    predict,
    start_tracks,
    step_anonymous,
    step_labelled,
    update,
)

# Walking only: switching never happens, the gate never fires and every fix is as wide as
# it says (the steady hypothesis never weighs).
CV_ONLY = TrackerSettings(
    mean_dwell_s=1e12,
    gate_probability=1.0 - 1e-15,
    max_speed_mps=50.0,
    steady_fix_probability=1e-300,
)


def _walking_only(bank: TrackBank) -> TrackBank:
    probabilities = np.tile([0.0, 1.0], (bank.size, 1))
    return dataclasses.replace(bank, model_probabilities=probabilities)


def _textbook_kalman(
    x: np.ndarray,
    p: np.ndarray,
    fixes: np.ndarray,
    noise: np.ndarray,
    times: np.ndarray,
    accel: float,
) -> list[np.ndarray]:
    """A constant-velocity Kalman filter written out plainly (one target, explicit inverse)."""
    h = np.hstack((np.eye(2), np.zeros((2, 2))))
    out = []
    for k in range(1, times.size):
        dt = times[k] - times[k - 1]
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        block = accel**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        q = np.kron(block, np.eye(2))
        x = f @ x
        p = f @ p @ f.T + q
        s = h @ p @ h.T + noise[k]
        gain = p @ h.T @ np.linalg.inv(s)
        x = x + gain @ (fixes[k] - h @ x)
        p = (np.eye(4) - gain @ h) @ p
        out.append(x.copy())
    return out


def test_walking_model_alone_is_the_textbook_kalman_filter(rng: np.random.Generator) -> None:
    times = np.cumsum(rng.uniform(0.1, 0.4, 30))  # irregular steps: each fix brings its time
    truth = np.column_stack((0.5 + 1.2 * times, 2.0 - 0.4 * times))
    sds = rng.uniform(0.02, 0.08, times.size)
    noise = sds[:, None, None] ** 2 * np.eye(2)
    fixes = truth + sds[:, None] * rng.standard_normal(truth.shape)
    bank = _walking_only(start_tracks(fixes[:1], noise[:1], times[:1], CV_ONLY))
    x0 = bank.means[0, 1].copy()
    p0 = bank.covariances[0, 1].copy() - CV_ONLY.min_measurement_sd_m**2 * np.diag([0, 0, 0, 0])
    floored = noise + CV_ONLY.min_measurement_sd_m**2 * np.eye(2)
    expected = _textbook_kalman(x0, p0, fixes, floored, times, CV_ONLY.walking_accel_sd_mps2)
    for k in range(1, times.size):
        bank = _walking_only(predict(bank, times[k : k + 1], CV_ONLY))
        bank = update(bank, fixes[k : k + 1], noise[k : k + 1], CV_ONLY).bank
        mean, _ = combined(_walking_only(bank))
        assert_allclose(mean[0], expected[k - 1], rtol=1e-9, atol=1e-9)


def _gaussian(innovation: np.ndarray, spread: np.ndarray) -> float:
    return float(
        np.exp(-0.5 * innovation @ np.linalg.solve(spread, innovation))
        / (2.0 * np.pi * np.sqrt(np.linalg.det(spread)))
    )


def test_a_fix_is_steady_noise_or_as_wide_as_it_says_weighed_by_likelihood() -> None:
    """The two-hypothesis update against a Gaussian-sum update written out plainly; the
    steady hypothesis's prior odds are the setting's, divided by how many times the track's
    usual stated sd the fix says its sd is."""
    settings = dataclasses.replace(CV_ONLY, steady_fix_probability=0.3)
    level = 0.01**2  # the track's learned noise level, per axis
    usual = 0.005  # what the track's fixes usually say, per axis, m^2
    stated = np.array([[[0.04, 0.01], [0.01, 0.02]]])  # what the fix says, m^2
    start = start_tracks(np.array([[1.0, 2.0]]), 1e-3 * np.eye(2)[None], np.zeros(1), settings)
    bank = dataclasses.replace(start, noise_var=np.array([level]), stated_var=np.array([usual]))
    predicted = _walking_only(predict(_walking_only(bank), np.array([0.3]), settings))
    for fix in (np.array([[1.03, 2.02]]), np.array([[1.4, 1.7]])):  # near, then far
        result = update(predicted, fix, stated, settings)
        x, p = predicted.means[0, 1], predicted.covariances[0, 1]
        h = np.hstack((np.eye(2), np.zeros((2, 2))))
        floored = stated[0] + settings.min_measurement_sd_m**2 * np.eye(2)
        steady = floored * min(1.0, level / (np.trace(floored) / 2.0))
        odds = 0.3 / 0.7 / np.sqrt((np.trace(floored) / 2.0) / usual)
        parts = []
        for noise, prior in ((steady, odds / (1.0 + odds)), (floored, 1.0 / (1.0 + odds))):
            s = h @ p @ h.T + noise
            gain = p @ h.T @ np.linalg.inv(s)
            nu = fix[0] - h @ x
            parts.append((prior * _gaussian(nu, s), x + gain @ nu, p - gain @ s @ gain.T))
        total = sum(w for w, _, _ in parts)
        mean = sum(w * m for w, m, _ in parts) / total
        cov = sum(w * (c + np.outer(m - mean, m - mean)) for w, m, c in parts) / total
        assert_allclose(result.bank.means[0, 1], mean, rtol=1e-9, atol=1e-12)
        assert_allclose(result.bank.covariances[0, 1], cov, rtol=1e-7, atol=1e-12)


def test_a_track_learns_how_widely_its_fixes_really_scatter(rng: np.random.Generator) -> None:
    """Fixes that say 20 cm but scatter by 2 cm: the track learns about 2 cm, and its
    reported covariance adds back what the stated spread says beyond it."""
    settings = TrackerSettings()
    stated = np.tile(0.2**2 * np.eye(2), (1, 1, 1))
    truth = np.array([[2.0, 1.5]])
    tracks, rows = Tracks.empty(), np.array([-1])
    for k in range(150):
        fix = truth + 0.02 * rng.standard_normal((1, 2))
        step = step_labelled(tracks, rows, fix, stated, 0.2 * k, settings)
        tracks, rows = step.tracks, step.fix_rows
    learned = float(np.sqrt(tracks.bank.noise_var[0]))
    assert 0.01 < learned < 0.04, learned
    mean, covariance = combined(tracks.bank)
    shown_mean, shown = estimates(tracks.bank)
    assert_allclose(shown_mean, mean)
    shared = tracks.bank.stated_var[0] - tracks.bank.noise_var[0]
    assert_allclose(shown[0, :2, :2], covariance[0, :2, :2] + shared * np.eye(2))
    assert_allclose(tracks.bank.stated_var[0], 0.2**2 + settings.min_measurement_sd_m**2)
    # Anonymous fixes (maybe another terminal's) teach nothing: nothing is added.
    anonymous = step_anonymous(Tracks.empty(), truth, stated, 0.0, settings).tracks
    for k in range(1, 20):
        fix = truth + 0.02 * rng.standard_normal((1, 2))
        anonymous = step_anonymous(anonymous, fix, stated, 0.2 * k, settings).tracks
    assert_allclose(estimates(anonymous.bank)[1], combined(anonymous.bank)[1])


def test_a_track_stored_before_it_learned_starts_from_the_next_fix() -> None:
    settings = TrackerSettings()
    noise = np.array([[[0.01, 0.0], [0.0, 0.02]]])
    bank = start_tracks(np.array([[1.0, 1.0]]), noise, np.zeros(1), settings)
    predicted = predict(bank, np.array([0.2]), settings)
    unknown = dataclasses.replace(
        predicted, noise_var=np.array([np.nan]), stated_var=np.array([np.nan])
    )
    fix = np.array([[1.05, 0.97]])
    fresh = update(predicted, fix, noise, settings).bank
    resumed = update(unknown, fix, noise, settings).bank
    assert_allclose(resumed.means, fresh.means)
    assert_allclose(resumed.noise_var, fresh.noise_var)
    assert_allclose(resumed.stated_var, fresh.stated_var)


def test_a_wild_fix_moves_the_track_as_a_fix_on_the_gate() -> None:
    settings = dataclasses.replace(CV_ONLY, gate_probability=0.99, max_speed_mps=3.0)
    bank = _walking_only(
        start_tracks(np.zeros((1, 2)), 1e-4 * np.eye(2)[None], np.zeros(1), settings)
    )
    predicted = _walking_only(predict(bank, np.array([0.2]), settings))
    far = np.array([[3.0, 0.0]])
    noise = 1e-4 * np.eye(2)[None]
    result = update(predicted, far, noise, settings)
    assert result.wild.tolist() == [True]
    # Closed form: the innovation covariance is scaled by d2 / gate.
    p = predicted.covariances[0, 1]
    s = p[:2, :2] + noise[0] + settings.min_measurement_sd_m**2 * np.eye(2)
    nu = far[0] - predicted.means[0, 1, :2]
    d2 = nu @ np.linalg.solve(s, nu)
    gain = p[:, :2] @ np.linalg.inv(s * d2 / settings.gate_chi2)
    expected = predicted.means[0, 1] + gain @ nu
    assert_allclose(result.bank.means[0, 1], expected, rtol=1e-9)
    moved = np.linalg.norm(result.bank.means[0, 1, :2])
    assert moved < 0.5 * np.linalg.norm(far)  # inflated, not trusted
    assert moved > 0.0  # and not dropped


@pytest.mark.parametrize(
    ("settings", "restarts"),
    [
        (TrackerSettings(), False),  # the walking model follows the inflated fixes
        # A track too slow to follow the jump: only the restart brings it there.
        (
            TrackerSettings(max_speed_mps=0.5, walking_accel_sd_mps2=0.1, start_speed_sd_mps=0.1),
            True,
        ),
    ],
    ids=["walking", "slow"],
)
def test_a_track_cannot_lock_out_a_terminal_that_moved(
    settings: TrackerSettings, restarts: bool
) -> None:
    noise = 1e-4 * np.eye(2)[None]
    here = np.array([[1.0, 1.0]])
    tracks = step_labelled(Tracks.empty(), np.array([-1]), here, noise, 0.0, settings).tracks
    for k in range(1, 4):
        tracks = step_labelled(tracks, np.array([0]), here, noise, 0.2 * k, settings).tracks
    teleported = np.array([[3.5, 3.0]])
    wild = []
    for k in range(settings.reset_after_wild):
        step = step_labelled(tracks, np.array([0]), teleported, noise, 1.0 + 0.2 * k, settings)
        wild.append(bool(step.wild[0]))
        tracks = step.tracks
    assert wild[0]
    mean, _ = combined(tracks.bank)
    assert np.linalg.norm(mean[0, :2] - teleported[0]) < 0.05
    assert all(wild) == restarts
    if restarts:  # at the newest fix exactly, its wild streak over
        assert_allclose(mean[0, :2], teleported[0])
        assert tracks.bank.wild.tolist() == [0]


def test_a_fix_older_than_the_track_does_not_move_it() -> None:
    settings = TrackerSettings()
    noise = 1e-4 * np.eye(2)[None]
    tracks = step_labelled(
        Tracks.empty(), np.array([-1]), np.array([[1.0, 1.0]]), noise, 10.0, settings
    ).tracks
    step = step_labelled(tracks, np.array([0]), np.array([[2.0, 2.0]]), noise, 9.0, settings)
    assert step.moved.tolist() == [False]
    assert_allclose(step.tracks.bank.means, tracks.bank.means)
    assert step.tracks.updates.tolist() == [1]


def test_standing_still_averages_fixes_down(rng: np.random.Generator) -> None:
    settings = TrackerSettings()
    sd = 0.05
    noise = np.tile(sd**2 * np.eye(2), (1, 1, 1))
    truth = np.array([[2.0, 1.5]])
    tracks = Tracks.empty()
    rows = np.array([-1])
    raw_errors, tracked_errors = [], []
    for k in range(200):
        fix = truth + sd * rng.standard_normal((1, 2))
        step = step_labelled(tracks, rows, fix, noise, 0.2 * k, settings)
        tracks, rows = step.tracks, step.fix_rows
        if k >= 20:
            raw_errors.append(np.linalg.norm(fix - truth))
            tracked_errors.append(np.linalg.norm(combined(tracks.bank)[0][0, :2] - truth))
    ratio = np.sqrt(np.mean(np.square(tracked_errors)) / np.mean(np.square(raw_errors)))
    assert ratio < 0.5, ratio


def test_association_follows_the_predictions_and_starts_tentative_tracks() -> None:
    settings = TrackerSettings()
    noise = np.tile(1e-4 * np.eye(2), (2, 1, 1))
    first = np.array([[1.0, 1.0], [3.0, 3.0]])
    step = step_anonymous(Tracks.empty(), first, noise, 0.0, settings)
    assert step.tracks.size == 2 and step.tracks.status.tolist() == [TENTATIVE, TENTATIVE]
    swapped = np.array([[3.02, 3.0], [1.0, 1.02]])  # the solver's order means nothing
    step = step_anonymous(step.tracks, swapped, noise, 0.2, settings)
    assert step.fix_rows.tolist() == [1, 0]
    far = np.vstack((swapped, [[0.2, 3.8]]))
    step = step_anonymous(step.tracks, far, np.tile(1e-4 * np.eye(2), (3, 1, 1)), 0.4, settings)
    assert step.fix_rows.tolist() == [1, 0, 2]
    assert step.tracks.status.tolist() == [CONFIRMED, CONFIRMED, TENTATIVE]


def test_associate_leaves_fixes_outside_every_gate() -> None:
    settings = TrackerSettings()
    bank = start_tracks(np.array([[1.0, 1.0]]), 1e-4 * np.eye(2)[None], np.zeros(1), settings)
    rows, cols = associate(bank, np.array([[3.0, 3.0]]), 1e-4 * np.eye(2)[None], settings)
    assert rows.size == 0 and cols.size == 0


def test_lifecycle_by_time_and_by_misses() -> None:
    settings = TrackerSettings(lost_after_s=2.0, drop_after_s=10.0, tentative_max_misses=2)
    noise = 1e-4 * np.eye(2)[None]
    step = step_anonymous(Tracks.empty(), np.array([[1.0, 1.0]]), noise, 0.0, settings)
    for k in range(2):  # solves that see nothing
        step = step_anonymous(
            step.tracks, np.zeros((0, 2)), np.zeros((0, 2, 2)), 0.2 * (k + 1), settings
        )
    status, removed = age_tracks(step.tracks, 0.4, settings)
    assert removed.tolist() == [True]  # tentative and missed twice
    labelled = step_labelled(
        Tracks.empty(), np.array([-1]), np.array([[1.0, 1.0]]), noise, 0.0, settings
    )
    status, removed = age_tracks(labelled.tracks, 3.0, settings)
    assert status.tolist() == [LOST] and removed.tolist() == [False]
    status, removed = age_tracks(labelled.tracks, 10.5, settings)
    assert removed.tolist() == [True]


def test_an_anonymous_track_missed_twice_is_lost_and_claimed_again() -> None:
    settings = TrackerSettings(confirm_after_updates=1)
    noise = 1e-4 * np.eye(2)[None]
    here = np.array([[1.0, 1.0]])
    step = step_anonymous(Tracks.empty(), here, noise, 0.0, settings)
    assert step.tracks.status.tolist() == [CONFIRMED]
    statuses = []
    for k in range(settings.lost_after_misses):  # solves that see nothing
        step = step_anonymous(
            step.tracks, np.zeros((0, 2)), np.zeros((0, 2, 2)), 0.2 * (k + 1), settings
        )
        statuses.append(int(step.tracks.status[0]))
    assert statuses == [CONFIRMED] * (settings.lost_after_misses - 1) + [LOST]
    step = step_anonymous(step.tracks, here, noise, 1.0, settings)
    assert step.fix_rows.tolist() == [0] and step.tracks.status.tolist() == [CONFIRMED]


def test_settings_refuse_inconsistent_values() -> None:
    with pytest.raises(VLPError, match="drop_after_s"):
        TrackerSettings(lost_after_s=10.0, drop_after_s=5.0)
    with pytest.raises(VLPError, match="max_speed_mps"):
        TrackerSettings(max_speed_mps=0.0)
    with pytest.raises(VLPError, match="rival_decision_ratio"):
        TrackerSettings(rival_decision_ratio=1.0)


def test_gospa_against_its_closed_form() -> None:
    truth = np.array([[0.0, 0.0], [5.0, 5.0]])
    estimates = np.array([[0.3, 0.4], [9.0, 9.0], [5.0, 5.6]])
    score = gospa(truth, estimates, cutoff_m=1.0)
    # Pairs: (0, 0) at 0.5 m, (1, 2) at 0.6 m; the third estimate is false.
    assert_allclose(score.localisation, 0.25 + 0.36)
    assert score.missed == 0.0
    assert_allclose(score.false, 0.5)
    assert_allclose(score.distance, np.sqrt(0.25 + 0.36 + 0.5))
    far = gospa(truth[:1], np.array([[3.0, 0.0]]), cutoff_m=1.0)
    assert (far.missed, far.false, far.localisation) == (0.5, 0.5, 0.0)


def _crossing(gap_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Two walkers on parallel lines ``gap_m`` apart, walking towards each other at 1.4 m/s
    and passing mid-way, at 5 Hz: times (T,) and true positions (T, 2, 2)."""
    times = np.arange(40) * 0.2
    along = 0.5 + 1.4 * times
    first = np.column_stack((along, np.full(times.size, 2.0)))
    second = np.column_stack((along[::-1], np.full(times.size, 2.0 + gap_m)))
    return times, np.stack((first, second), axis=1)


def test_walkers_who_cross_keep_their_tracks(rng: np.random.Generator) -> None:
    settings = TrackerSettings()
    times, truth = _crossing(0.3)
    noise = np.tile(0.02**2 * np.eye(2), (2, 1, 1))
    tracks, owners = Tracks.empty(), []
    for k, time_s in enumerate(times):
        order = rng.permutation(2)  # an aggregated solve's order means nothing
        fixes = truth[k, order] + 0.02 * rng.standard_normal((2, 2))
        step = step_anonymous(tracks, fixes, noise, float(time_s), settings)
        tracks = step.tracks
        rows = np.empty(2, dtype=np.intp)
        rows[order] = step.fix_rows  # each walker's track at this instant
        owners.append(rows)
    # The expectation is the truth's own identities: each walker keeps the track it started.
    assert tracks.size == 2
    assert np.all(np.array(owners) == owners[0])
    mean, _ = combined(tracks.bank)
    assert_allclose(mean[owners[0], :2], truth[-1], atol=0.08)


def _head_on_swaps(settings: TrackerSettings, crossings: int, seed: int) -> int:
    """Of ``crossings`` passes of two walkers head-on on one line (fixes 3 cm off, in a
    random order), how many end with the walkers' tracks traded."""
    rng = np.random.default_rng(seed)
    times, truth = _crossing(0.0)
    noise = np.tile(0.03**2 * np.eye(2), (2, 1, 1))
    swapped = 0
    for _ in range(crossings):
        tracks, owners = Tracks.empty(), []
        for k, time_s in enumerate(times):
            order = rng.permutation(2)
            fixes = truth[k, order] + 0.03 * rng.standard_normal((2, 2))
            step = step_anonymous(tracks, fixes, noise, float(time_s), settings)
            tracks = step.tracks
            rows = np.empty(2, dtype=np.intp)
            rows[order] = step.fix_rows
            owners.append(rows)
        assert tracks.size == 2
        swapped += int(np.any(owners[-1] != owners[5]))  # from confirmation to the end
    return swapped


def test_walkers_who_meet_head_on_keep_their_tracks_when_both_ways_are_followed() -> None:
    # Where they meet, positions cannot tell the walkers apart and the assignment often
    # takes the swap; the next fixes, which go on along each walker's line, tell the swap.
    # Never taking the other way (a decision ratio no evidence reaches) is the tracker
    # without it.
    kept_only = TrackerSettings(rival_decision_ratio=1e300)
    assert _head_on_swaps(kept_only, 30, seed=1) >= 3
    assert _head_on_swaps(TrackerSettings(), 30, seed=1) == 0


def test_the_other_way_is_followed_from_an_ambiguous_solve_and_forgotten_later() -> None:
    settings = TrackerSettings()
    times, truth = _crossing(0.0)
    noise = np.tile(0.03**2 * np.eye(2), (2, 1, 1))
    tracks = Tracks.empty()
    paired_at = []
    for k, time_s in enumerate(times):
        before = tracks
        tracks = step_anonymous(tracks, truth[k], noise, float(time_s), settings).tracks
        if tracks.rivals is not None and np.all(tracks.rivals.pair == 1):
            paired_at.append(k)
            if before.rivals is None:  # the pair's first solve: each track's other state
                # is its own update with the other walker's fix
                other = update(
                    predict(before.bank, np.full(2, time_s), settings),
                    truth[k, ::-1],
                    noise,
                    settings,
                    np.full(2, 0.2),
                    learn=False,
                    inflate_chi2=settings.anonymous_inflate_chi2,
                ).bank
                assert_allclose(tracks.rivals.bank.means, other.means, atol=1e-12)
    # Paired only where the walkers are within a metre (each walks 0.28 m per solve; they
    # meet between solves 19 and 20), for no more than rival_memory_solves solves; the
    # fixes after the meeting settle it (exact fixes: the kept way was right).
    assert paired_at
    assert all(abs(k - 19.5) * 2 * 0.28 < 1.0 for k in paired_at)
    assert len(paired_at) <= settings.rival_memory_solves
    assert tracks.rivals is None


def test_a_track_confirmed_where_one_was_lost_takes_its_place() -> None:
    settings = TrackerSettings(confirm_after_updates=3)
    noise = 1e-4 * np.eye(2)[None]
    here = np.array([[1.0, 1.0]])
    tracks, time_s = Tracks.empty(), 0.0
    for _ in range(5):  # a standing terminal, confirmed
        time_s += 0.2
        tracks = step_anonymous(tracks, here, noise, time_s, settings).tracks
    for k in range(10):  # fixes that walk away at 1 m/s pull its track half a metre off
        time_s += 0.05
        there = here + np.array([[0.05 * (k + 1), 0.0]])
        tracks = step_anonymous(tracks, there, noise, time_s, settings).tracks
    mean, _ = combined(tracks.bank)
    assert tracks.size == 1 and tracks.status[0] == CONFIRMED
    assert_allclose(mean[0, :2], there[0], atol=0.02)
    # The terminal's own fixes again, 0.06 s apart: beyond reach of the pulled track, which
    # is predicted to walk on (0.55 m and more away, reach 3 m/s x 0.06 s per solve), they
    # start a tentative track, which on confirmation continues the coasting one in its row
    # (0.18 s after its last fix: 0.54 m, plus the spread of both, from where it was). A
    # second terminal that appears 5 m away at the same time could not have come from it
    # and stays new.
    both = np.vstack((here, [[1.0, 6.0]]))
    for k in range(settings.confirm_after_updates):
        time_s += 0.06
        step = step_anonymous(tracks, both, np.tile(noise, (2, 1, 1)), time_s, settings)
        tracks = step.tracks
        status, removed = age_tracks(tracks, time_s, settings)
        if k < settings.confirm_after_updates - 1:
            assert step.fix_rows.tolist() == [1, 2] and not np.any(removed)
    assert step.fix_rows.tolist() == [0, 2]
    assert removed.tolist() == [False, True, False]
    assert status.tolist() == [CONFIRMED, TENTATIVE, CONFIRMED]
    mean, _ = combined(tracks.bank)
    assert_allclose(mean[0, :2], here[0], atol=0.02)


def test_association_weighs_each_model_by_its_own_likelihood(rng: np.random.Generator) -> None:
    # Every pair within the gate: the assignment is the permutation of greatest likelihood,
    # each fix's likelihood being the models' densities weighed by their probabilities.
    from itertools import permutations

    from scipy.stats import multivariate_normal

    settings = TrackerSettings(gate_probability=1.0 - 1e-15)
    for _ in range(20):
        n = 3
        roots = rng.normal(0.0, 0.15, (n, N_MODELS, 4, 4))
        bank = TrackBank(
            means=rng.uniform(0.0, 1.0, (n, N_MODELS, 4)),
            covariances=roots @ np.swapaxes(roots, -1, -2) + 1e-3 * np.eye(4),
            model_probabilities=rng.dirichlet([1.0, 1.0], n),
            times_s=np.zeros(n),
            wild=np.zeros(n, dtype=np.intp),
            noise_var=np.full(n, np.nan),
            stated_var=np.full(n, np.nan),
            offset=np.zeros((n, 2)),
        )
        fixes = rng.uniform(0.0, 1.0, (n, 2))
        noise = np.tile(0.01 * np.eye(2), (n, 1, 1))
        floored = noise + settings.min_measurement_sd_m**2 * np.eye(2)
        density = np.array(
            [
                [
                    sum(
                        bank.model_probabilities[t, k]
                        * multivariate_normal.pdf(
                            fixes[f],
                            bank.means[t, k, :2],
                            bank.covariances[t, k, :2, :2] + floored[f],
                        )
                        for k in range(N_MODELS)
                    )
                    for f in range(n)
                ]
                for t in range(n)
            ]
        )
        best = max(permutations(range(n)), key=lambda p: np.prod(density[range(n), p]))
        rows, cols = associate(bank, fixes, noise, settings)
        assert rows.tolist() == [0, 1, 2] and cols.tolist() == list(best)


def _side_by_side_with_a_shadowed_pair(
    settings: TrackerSettings,
) -> tuple[list[np.ndarray], Tracks]:
    """Two walkers 0.6 m apart walking side by side at 1.4 m/s, fixes 2 cm off at 5 Hz; two
    solves in a row (a shadowed terminal throws an aggregated solve's every estimate) put
    both estimates 0.5 m across, saying 10 cm. Each walker's track row at every instant."""
    rng = np.random.default_rng(3)
    times = np.arange(30) * 0.2
    along = 0.5 + 1.4 * times
    truth = np.stack(
        (np.column_stack((along, np.zeros(30))), np.column_stack((along, np.full(30, 0.6)))),
        axis=1,
    )
    tracks, owners = Tracks.empty(), []
    for k, time_s in enumerate(times):
        order = rng.permutation(2)
        if k in (15, 16):
            fixes, sd = truth[k, order] + [0.0, 0.5], 0.1
        else:
            fixes, sd = truth[k, order] + 0.02 * rng.standard_normal((2, 2)), 0.03
        noise = np.tile(sd**2 * np.eye(2), (2, 1, 1))
        step = step_anonymous(tracks, fixes, noise, float(time_s), settings)
        tracks = step.tracks
        rows = np.empty(2, dtype=np.intp)
        rows[order] = step.fix_rows
        owners.append(rows)
    return owners, tracks


def test_wrong_estimates_of_a_shadowed_solve_do_not_swap_identities() -> None:
    settings = TrackerSettings()
    owners, tracks = _side_by_side_with_a_shadowed_pair(settings)
    # Each walker keeps the track it had before the shadowed solves, to the end.
    assert tracks.size == 2
    assert all(rows.tolist() == owners[0].tolist() for rows in owners)
    # The same estimates inflated only to the gate (as a labelled fix is) drag the first
    # walker's track onto the second and the two trade identities: the expectation above is
    # not met by any tracker.
    at_gate = dataclasses.replace(settings, anonymous_inflate_probability=settings.gate_probability)
    owners_at_gate, _ = _side_by_side_with_a_shadowed_pair(at_gate)
    assert owners_at_gate[-1].tolist() != owners_at_gate[0].tolist()


def test_a_doubtful_anonymous_fix_moves_its_track_as_one_on_the_anonymous_bound() -> None:
    # Closed form (walking model alone, no switching): a fix another track explains better
    # than its own (it was assigned to the first track only because the second has a fix of
    # its own) and beyond the anonymous bound moves the first track as a Kalman update whose
    # innovation covariance is, with even odds, as the fix states it or scaled to put the fix
    # on the bound (the two collapsed by their likelihoods). Alone, with no other track to
    # doubt it for, the same fix is a plain Kalman update.
    settings = TrackerSettings(mean_dwell_s=1e12, anonymous_inflate_probability=0.5)
    noise = np.tile(0.01 * np.eye(2), (2, 1, 1))
    starts = np.array([[0.0, 0.0], [1.0, 0.6]])
    fixes = np.array([[0.5, 0.2], [1.0, 0.6]])
    bank = _walking_only(start_tracks(starts, noise, np.zeros(2), settings))
    predicted = predict(bank, np.full(2, 0.2), settings)
    prior = predicted.covariances[0, 1]
    whole = prior[:2, :2] + noise[0] + settings.min_measurement_sd_m**2 * np.eye(2)
    nu = fixes[0] - predicted.means[0, 1, :2]
    d2 = float(nu @ np.linalg.solve(whole, nu))
    assert settings.anonymous_inflate_chi2 < d2 < settings.gate_chi2

    def kalman(innovation_covariance: np.ndarray) -> np.ndarray:
        gain = prior[:, :2] @ np.linalg.inv(innovation_covariance)
        return np.asarray(predicted.means[0, 1] + gain @ nu)

    confirmed = np.array([CONFIRMED, CONFIRMED])
    both = Tracks(bank, confirmed, np.array([3, 3]), np.zeros(2, dtype=np.intp))
    step = step_anonymous(both, fixes, noise, 0.2, settings)
    assert step.fix_rows.tolist() == [0, 1]
    assert not np.any(step.wild)  # within the gate: not counted towards a restart
    spreads = (whole, d2 / settings.anonymous_inflate_chi2 * whole)
    weights = np.array([_gaussian(nu, spread) for spread in spreads])
    weights /= weights.sum()
    collapsed = sum(w * kalman(spread) for w, spread in zip(weights, spreads, strict=True))
    assert_allclose(step.tracks.bank.means[0, 1], collapsed, rtol=1e-9, atol=1e-12)

    alone = Tracks(bank.take(np.array([0])), confirmed[:1], np.array([3]), np.zeros(1, np.intp))
    step = step_anonymous(alone, fixes[:1], noise[:1], 0.2, settings)
    assert_allclose(step.tracks.bank.means[0, 1], kalman(whole), rtol=1e-9, atol=1e-12)


# Runs off: the odds of walking are never raised.
NO_RUNS = TrackerSettings(start_run_ratio=1.0)


def _after_fixes(
    offsets: list[float], stated_sd: list[float], settings: TrackerSettings
) -> TrackBank:
    """A track that stood 2 s at (1, 1) (fixes scattered by 1 cm and saying 2.5 cm), then
    fixes ``offsets`` metres along x, each saying ``stated_sd``."""
    gen = np.random.default_rng(5)
    here = np.array([[1.0, 1.0]])
    fixes = [here + 0.01 * gen.standard_normal((1, 2)) for _ in range(10)]
    fixes += [here + np.array([[dx, 0.0]]) for dx in offsets]
    stated = [0.025] * 10 + stated_sd
    tracks, rows = Tracks.empty(), np.array([-1])
    for k, (fix, sd) in enumerate(zip(fixes, stated, strict=True)):
        step = step_labelled(tracks, rows, fix, np.array([sd**2 * np.eye(2)]), 0.2 * k, settings)
        tracks, rows = step.tracks, step.fix_rows
    return tracks.bank


def test_a_standing_terminal_that_sets_off_is_followed_from_its_second_far_fix() -> None:
    # A walker sets off between two fixes: the first lands 8 cm out, the next 36 cm, and the
    # solver says 20-24 cm for both (8-10 times what the fixes that stood said). Alone, each is
    # as well a wide fix of a terminal that stands; the second further out along the first is
    # a start.
    offsets, stated = [0.08, 0.36], [0.20, 0.24]
    walked = _after_fixes(offsets, stated, TrackerSettings())
    plain = _after_fixes(offsets, stated, NO_RUNS)
    lag = 1.0 + offsets[-1] - estimates(walked)[0][0, 0]
    lag_plain = 1.0 + offsets[-1] - estimates(plain)[0][0, 0]
    assert walked.model_probabilities[0, 1] > 0.95 > plain.model_probabilities[0, 1]
    assert lag < 0.6 * lag_plain, (lag, lag_plain)


def test_a_wild_fix_that_repeats_does_not_start_a_walk() -> None:
    # A hand that stays on an LED: two fixes in a row land at the same wrong place. The second
    # is no further out than the first: the track stands as it would without runs.
    repeated = _after_fixes([0.3, 0.3], [0.1, 0.1], TrackerSettings())
    assert repeated.offset[0, 0] > TrackerSettings().start_run_sd
    plain = _after_fixes([0.3, 0.3], [0.1, 0.1], NO_RUNS)
    assert_allclose(repeated.means, plain.means)
    assert_allclose(repeated.model_probabilities, plain.model_probabilities)


def test_a_far_fix_that_says_what_the_others_said_is_taken_for_a_first_step() -> None:
    # A track stood 2 s (fixes scattered by 1 cm, each saying 2.5 cm); the next fix lands 8 cm
    # out, some 4 sds of the noise the track has seen. Saying 2.5 cm as the others did, it is
    # likelier a first step than a wide fix of a terminal that still stands: the track goes
    # more than half-way to it at once, before any run. The same fix saying 10 cm (as a
    # shadowed LED makes a fix say) may well be a wide one, and moves the track less.
    far, usual, wide = 0.08, 0.025, 0.10
    steady = _after_fixes([far], [usual], TrackerSettings())
    moved = estimates(steady)[0][0, 0] - 1.0
    assert far > 3.0 * np.sqrt(steady.noise_var[0])
    assert moved > 0.5 * far
    doubtful = _after_fixes([far], [wide], TrackerSettings())
    assert estimates(doubtful)[0][0, 0] - 1.0 < 0.5 * moved


def _set_off_beside_a_lost_track(seed: int) -> list[int]:
    """The rows that claim a terminal's fixes as it sets off towards where a track was lost.

    Two terminals stand 1.8 m apart (fixes: truth plus Gaussian noise of sd 2 cm, stated sd
    3 cm); the second leaves the solves, and its track, missed, is lost and spreads. After
    2.4 s the first walks towards it at 1.4 m/s; its first fix of the walk is shadowed: 0.8 m
    further along, stating sd 0.2 m (beyond its standing track's gate, within its reach).
    """
    rng = np.random.default_rng(seed)
    settings = TrackerSettings()
    noise = (0.03**2) * np.eye(2)
    walker, other = np.array([1.0, 1.0]), np.array([2.5, 2.0])
    heading = (other - walker) / np.linalg.norm(other - walker)
    tracks, time_s = Tracks.empty(), 0.0

    def solve(positions: np.ndarray, covariances: np.ndarray) -> np.ndarray:
        nonlocal tracks
        step = step_anonymous(tracks, positions, covariances, time_s, settings)
        status, removed = age_tracks(step.tracks, time_s, settings)
        tracks = dataclasses.replace(step.tracks, status=status)
        rows = step.fix_rows
        if np.any(removed):
            kept = np.cumsum(~removed) - 1
            tracks, rows = tracks.take(~removed), kept[rows]
        return rows

    for _ in range(10):  # both stand: two confirmed tracks
        time_s += 0.2
        truth = np.vstack((walker, other))
        solve(truth + rng.normal(0.0, 0.02, truth.shape), np.tile(noise, (2, 1, 1)))
    for _ in range(12):  # the second is no longer seen: its track is lost
        time_s += 0.2
        rows = solve(walker + rng.normal(0.0, 0.02, (1, 2)), noise[None])
    claimed = [int(rows[0])]
    time_s += 0.2
    shadowed = walker + (0.28 + 0.8) * heading
    claimed.append(int(solve(shadowed[None], (0.2**2) * np.eye(2)[None])[0]))
    for k in range(2, 8):  # the walk, clean fixes
        time_s += 0.2
        here = walker + 0.28 * k * heading
        claimed.append(int(solve(here + rng.normal(0.0, 0.02, (1, 2)), noise[None])[0]))
    return claimed


@pytest.mark.parametrize("seed", range(5))
def test_a_lost_track_does_not_claim_a_fix_a_confirmed_one_reaches(seed: int) -> None:
    # The lost track, spread wide, explains the shadowed fix better than the standing track
    # it is 1 m from; if it took the fix, the walker's next fixes would follow it and the
    # walker would show under the lost track's id. A confirmed track claims first.
    claimed = _set_off_beside_a_lost_track(seed)
    assert claimed == [claimed[0]] * len(claimed)
