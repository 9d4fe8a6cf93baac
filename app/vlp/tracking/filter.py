"""The filter: a standing / walking mixture of two Kalman filters per track, all tracks at once.

State ``[x, y, vx, vy]`` (metres, m/s). Model 0 (standing) keeps the position up to a slow
drift and lets the velocity fall to zero; model 1 (walking) is constant velocity with
white-noise acceleration. The interacting multiple model (IMM) filter mixes the two by their
probabilities at every step (Blom and Bar-Shalom, IEEE TAC 33(8), 1988). Every function takes
and returns whole batches of arrays: ``n`` tracks, never one Python object per track.

Each fix brings its own covariance (the solver's) and its own time: the step between two fixes
is the difference of their times, however irregular. A wild fix (innovation beyond the gate)
is not dropped: its covariance is inflated so that its innovation lies on the gate. A standing
track whose fixes run away from it in one direction has set off (:mod:`.starts`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..typing import BoolArray, FloatArray
from .bank import N_MODELS, TrackBank
from .settings import TrackerSettings

__all__ = [
    "N_MODELS",
    "TrackBank",
    "Update",
    "combined",
    "estimates",
    "floored_covariances",
    "inverse_2x2",
    "predict",
    "start_tracks",
    "steady_probabilities",
    "update",
    "updated_tracks",
    "with_restarts",
]


def inverse_2x2(matrices: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Inverses and determinants of a stack of 2 x 2 matrices ``(..., 2, 2)`` (closed form)."""
    a, b = matrices[..., 0, 0], matrices[..., 0, 1]
    c, d = matrices[..., 1, 0], matrices[..., 1, 1]
    det = a * d - b * c
    inverse = np.stack((np.stack((d, -b), -1), np.stack((-c, a), -1)), -2) / det[..., None, None]
    return inverse, det


def floored_covariances(covariances: FloatArray, settings: TrackerSettings) -> FloatArray:
    """Fix covariances ``(m, 2, 2)`` (m^2) with ``min_measurement_sd_m`` added in quadrature."""
    return np.asarray(covariances + settings.min_measurement_sd_m**2 * np.eye(2))


def start_tracks(
    positions: FloatArray, covariances: FloatArray, times_s: FloatArray, settings: TrackerSettings
) -> TrackBank:
    """New tracks at fixes: position as fixed, speed unknown (sd ``max_speed_mps / 2``).

    Parameters
    ----------
    positions : ndarray of shape (m, 2), metres
    covariances : ndarray of shape (m, 2, 2), m^2 (floored here)
    times_s : ndarray of shape (m,), seconds
    settings : TrackerSettings

    Returns
    -------
    TrackBank
        ``m`` tracks, standing with probability ``settings.standing_prior``.
    """
    count = positions.shape[0]
    state = np.zeros((count, N_MODELS, 4))
    state[:, :, :2] = positions[:, None, :]
    covariance = np.zeros((count, N_MODELS, 4, 4))
    covariance[:, :, :2, :2] = floored_covariances(covariances, settings)[:, None]
    speed_var = (0.5 * settings.max_speed_mps) ** 2
    covariance[:, 1, 2, 2] = covariance[:, 1, 3, 3] = speed_var
    covariance[:, 0, 2, 2] = covariance[:, 0, 3, 3] = settings.start_speed_sd_mps**2
    prior = settings.standing_prior
    probabilities = np.tile([prior, 1.0 - prior], (count, 1))
    return TrackBank(
        means=state,
        covariances=covariance,
        model_probabilities=probabilities,
        times_s=np.asarray(times_s, dtype=np.float64).copy(),
        wild=np.zeros(count, dtype=np.intp),
        noise_var=np.trace(covariance[:, 0, :2, :2], axis1=1, axis2=2) / 2.0,
        stated_var=np.trace(covariance[:, 0, :2, :2], axis1=1, axis2=2) / 2.0,
        offset=np.zeros((count, 2)),
    )


def _process_noise(dt: FloatArray, settings: TrackerSettings) -> FloatArray:
    """Process noise ``(n, 2, 4, 4)`` of both models over ``dt``: standing, a slow drift of
    the position and the velocity it may set off with; walking, white-noise acceleration."""
    count = dt.shape[0]
    noise = np.zeros((count, N_MODELS, 4, 4))
    drift = settings.standing_drift_mps**2 * dt
    noise[:, 0, 0, 0] = noise[:, 0, 1, 1] = drift
    noise[:, 0, 2, 2] = noise[:, 0, 3, 3] = settings.start_speed_sd_mps**2
    accel = settings.walking_accel_sd_mps2**2
    noise[:, 1, 0, 0] = noise[:, 1, 1, 1] = accel * dt**3 / 3.0
    noise[:, 1, 0, 2] = noise[:, 1, 2, 0] = noise[:, 1, 1, 3] = noise[:, 1, 3, 1] = (
        accel * dt**2 / 2.0
    )
    noise[:, 1, 2, 2] = noise[:, 1, 3, 3] = accel * dt
    return noise


def _moved(
    means: FloatArray, covariances: FloatArray, dt: FloatArray, settings: TrackerSettings
) -> tuple[FloatArray, FloatArray]:
    """``F x`` and ``F P F^T + Q`` of both models over ``dt``, written out by 2 x 2 blocks
    (position, velocity): standing (``F = [[I, 0], [0, 0]]``) keeps the position and its
    velocity is the noise alone; walking (``F = [[I, dt I], [0, I]]``) moves the position by
    ``dt`` times the velocity. ``Q``: :func:`_process_noise`."""
    out_means = means.copy()
    out_means[:, 0, 2:] = 0.0
    out_means[:, 1, :2] += dt[:, None] * means[:, 1, 2:]
    out = _process_noise(dt, settings)  # every block below adds to its noise
    standing, walking = covariances[:, 0], covariances[:, 1]
    out[:, 0, :2, :2] += standing[:, :2, :2]
    t = dt[:, None, None]
    pp, pv = walking[:, :2, :2], walking[:, :2, 2:]
    vp, vv = walking[:, 2:, :2], walking[:, 2:, 2:]
    out[:, 1, :2, :2] += pp + t * (pv + vp) + (t * t) * vv
    out[:, 1, :2, 2:] += pv + t * vv
    out[:, 1, 2:, :2] += vp + t * vv
    out[:, 1, 2:, 2:] += vv
    return out_means, out


def _switching(dt: FloatArray, settings: TrackerSettings) -> FloatArray:
    """Model transition probabilities ``(n, 2, 2)`` (row: from, column: to) over ``dt``."""
    switch = -np.expm1(-dt / settings.mean_dwell_s)
    out = np.empty((dt.shape[0], N_MODELS, N_MODELS))
    out[:, 0, 0] = out[:, 1, 1] = 1.0 - switch
    out[:, 0, 1] = out[:, 1, 0] = switch
    return out


def predict(bank: TrackBank, times_s: FloatArray, settings: TrackerSettings) -> TrackBank:
    """Mix the two models and move every track to its new time (IMM interaction + prediction).

    Parameters
    ----------
    bank : TrackBank
        ``n`` tracks.
    times_s : ndarray of shape (n,), seconds
        Each track's new time; a time before the track's own is treated as no step.
    settings : TrackerSettings

    Returns
    -------
    TrackBank
        The predicted tracks (their ``model_probabilities`` are the predicted ones).
    """
    dt = np.maximum(np.asarray(times_s, dtype=np.float64) - bank.times_s, 0.0)
    mixing = bank.model_probabilities[:, :, None] * _switching(dt, settings)  # (n, i, j)
    predicted_probabilities = mixing.sum(axis=1)
    weights = mixing / predicted_probabilities[:, None, :]
    mixed = np.einsum("nij,nia->nja", weights, bank.means)
    spread = bank.means[:, :, None, :] - mixed[:, None, :, :]  # (n, i, j, 4)
    weighted = weights[..., None] * spread
    mixed_cov = (
        weights[:, 0, :, None, None] * bank.covariances[:, 0, None]
        + weights[:, 1, :, None, None] * bank.covariances[:, 1, None]
        + (weighted[..., :, None] * spread[..., None, :]).sum(axis=1)
    )
    means, covariances = _moved(mixed, mixed_cov, dt, settings)
    return TrackBank(
        means=_capped_speed(means, settings.max_speed_mps),
        covariances=covariances,
        model_probabilities=predicted_probabilities,
        times_s=np.maximum(np.asarray(times_s, dtype=np.float64), bank.times_s),
        wild=bank.wild,
        noise_var=bank.noise_var,
        stated_var=bank.stated_var,
        offset=bank.offset,
    )


def _capped_speed(means: FloatArray, max_speed: float) -> FloatArray:
    speed = np.hypot(means[..., 2], means[..., 3])
    factor = np.minimum(1.0, max_speed / np.maximum(speed, 1e-12))
    out = means.copy()
    out[..., 2:] *= factor[..., None]
    return out


def combined(bank: TrackBank) -> tuple[FloatArray, FloatArray]:
    """The mixture's mean ``(n, 4)`` and covariance ``(n, 4, 4)`` of every track."""
    weights = bank.model_probabilities
    mean = np.einsum("nm,nma->na", weights, bank.means)
    spread = bank.means - mean[:, None, :]
    covariance = np.einsum("nm,nmab->nab", weights, bank.covariances) + np.einsum(
        "nm,nma,nmb->nab", weights, spread, spread
    )
    return mean, covariance


def _combined_position(bank: TrackBank) -> FloatArray:
    """The position block ``(n, 2, 2)`` of :func:`combined`'s covariance."""
    weights = bank.model_probabilities
    position = bank.means[:, :, :2]
    spread = position - np.einsum("nm,nma->na", weights, position)[:, None, :]
    weighted = weights[:, :, None, None] * (
        bank.covariances[:, :, :2, :2] + spread[..., :, None] * spread[..., None, :]
    )
    return np.asarray(weighted.sum(axis=1))


@dataclass(frozen=True)
class Update:
    """The outcome of :func:`update`: the new tracks, which fixes were wild, which tracks
    restarted at their fix."""

    bank: TrackBank
    wild: BoolArray
    restarted: BoolArray


def update(
    predicted: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    settings: TrackerSettings,
    elapsed_s: FloatArray | None = None,
    *,
    learn: bool = True,
    inflate_chi2: float | FloatArray | None = None,
) -> Update:
    """Update each predicted track with its fix (row ``k`` with fix ``k``).

    A fix's error is either the terminal's usual noise (its stated covariance shrunk to the
    track's learned ``noise_var``) or as wide as its stated covariance says (a shadowed LED, a
    far optimum), the first with the prior probability :func:`steady_probabilities` gives (the
    wider a fix says it is than the track's fixes usually say, the likelier it is wide); each
    model's update weighs both by their likelihoods (a two-component Gaussian mixture,
    collapsed). Where ``learn`` is False both hypotheses weigh alike a priori. The solver
    widens a fix's covariance for what one fix cannot tell (its own few residual degrees of
    freedom): a track sees many fixes of one terminal and learns the level the fixes really
    scatter with, from the innovations.

    A fix whose squared Mahalanobis distance ``d2`` from the mixture's prediction (with its
    stated covariance) exceeds ``settings.gate_chi2`` gets the innovation covariance
    ``S (d2 / gate)``, i.e. its own covariance becomes ``(d2 / gate) S - P``: it moves the
    track as a fix on the gate would (``inflate_chi2`` in place of the gate, where given).
    After ``reset_after_wild`` wild fixes in a row the track restarts at the newest.

    Parameters
    ----------
    predicted : TrackBank
        ``n`` tracks predicted to their fixes' times (:func:`predict`).
    positions : ndarray of shape (n, 2), metres
    covariances : ndarray of shape (n, 2, 2), m^2
    settings : TrackerSettings
    elapsed_s : ndarray of shape (n,), seconds, default=None
        Time since each track's previous fix (how much the noise level may have changed);
        None: the learned levels move a share ``1 - 1/e`` of the way to the new fix's.
    learn : bool, default=True
        False: every fix is as wide as it says (the level follows the stated one, so
        :func:`estimates` adds nothing): for fixes that may be another terminal's.
    inflate_chi2 : float or ndarray of shape (n,), default=None
        The squared Mahalanobis distance a fix beyond it is inflated to, per fix or for all
        (None: the gate's,
        ``settings.gate_chi2``); which fixes count as wild (and restart a track after
        ``reset_after_wild`` in a row) is still decided by the gate.

    Returns
    -------
    Update
    """
    bank, wild = updated_tracks(
        predicted,
        positions,
        covariances,
        settings,
        elapsed_s,
        learn=learn,
        inflate_chi2=inflate_chi2,
    )
    return with_restarts(bank, wild, positions, covariances, settings)


def updated_tracks(
    predicted: TrackBank,
    positions: FloatArray,
    covariances: FloatArray,
    settings: TrackerSettings,
    elapsed_s: FloatArray | None,
    *,
    learn: bool,
    inflate_chi2: float | FloatArray | None,
) -> tuple[TrackBank, BoolArray]:
    """:func:`update` before the restarts: the updated tracks and which fixes were wild."""
    stated = floored_covariances(covariances, settings)
    prior = _combined_position(predicted)
    innovation = positions - np.einsum(
        "nm,nma->na", predicted.model_probabilities, predicted.means[:, :, :2]
    )
    whole = prior + stated
    a, b, d = whole[:, 0, 0], whole[:, 0, 1], whole[:, 1, 1]
    nu0, nu1 = innovation[:, 0], innovation[:, 1]
    distance2 = (d * nu0 * nu0 - 2.0 * b * nu0 * nu1 + a * nu1 * nu1) / (a * d - b * b)
    wild = distance2 > settings.gate_chi2
    inflate = np.broadcast_to(
        settings.gate_chi2 if inflate_chi2 is None else inflate_chi2, distance2.shape
    )
    outside = distance2 > inflate
    scale = np.where(outside, distance2 / inflate, 1.0)
    wide = np.where(outside[:, None, None], scale[:, None, None] * (prior + stated) - prior, stated)
    stated_var = (stated[:, 0, 0] + stated[:, 1, 1]) / 2.0
    level = np.where(np.isfinite(predicted.noise_var), predicted.noise_var, stated_var)
    shrink = np.minimum(1.0, level / stated_var) if learn else np.ones_like(stated_var)
    noises = np.stack((stated * shrink[:, None, None], wide), axis=1)  # (n, 2, 2, 2)
    before = np.where(np.isfinite(predicted.stated_var), predicted.stated_var, stated_var)
    steady = (
        steady_probabilities(stated_var, before, settings)
        if learn
        else np.full(stated_var.shape, 0.5)
    )
    means, covs, probabilities = _model_updates(predicted, positions, noises, steady)
    rate = _memory_rate(elapsed_s, level.shape[0], settings)
    stated_level = 1.0 / (1.0 / before + rate * (1.0 / stated_var - 1.0 / before))
    if learn:
        position = np.einsum("nm,nma->na", probabilities, means[:, :, :2])
        apart = means[:, :, :2] - position[:, None]
        # The trace of the updated mixture's position covariance.
        spread = covs[:, :, 0, 0] + covs[:, :, 1, 1] + np.einsum("nma,nma->nm", apart, apart)
        posterior_var = np.einsum("nm,nm->n", probabilities, spread) / 2.0
        residual = positions - position
        noise_var = _learned_level(level, residual, posterior_var, stated_var, rate, settings)
    else:
        noise_var = stated_level
    streak = np.where(wild, predicted.wild + 1, 0)
    bank = TrackBank(
        means=_capped_speed(means, settings.max_speed_mps),
        covariances=covs,
        model_probabilities=probabilities,
        times_s=predicted.times_s,
        wild=streak,
        noise_var=noise_var,
        stated_var=stated_level,
        offset=predicted.offset,
    )
    return bank, wild


def steady_probabilities(
    stated_var: FloatArray, usual_var: FloatArray, settings: TrackerSettings
) -> FloatArray:
    """Each fix's prior probability of being the track's usual noise (the steady hypothesis
    of :func:`update`) rather than as wide as it says.

    The odds ``steady_fix_probability / (1 - steady_fix_probability)`` of a fix that states
    the track's usual spread, times ``sqrt(usual_var / stated_var)``: a fix that says its sd
    is k times what the track's fixes usually say has 1/k of those odds. A shadowed LED widens
    the solver's covariance many times over and the fix is as far off as it says; a clean fix's
    stated spread wanders by a few times either way and says little of its error.

    Parameters
    ----------
    stated_var : ndarray of shape (n,), m^2
        Each fix's stated (floored) variance per axis.
    usual_var : ndarray of shape (n,), m^2
        The track's usual stated variance per axis (``TrackBank.stated_var`` before the fix).
    settings : TrackerSettings

    Returns
    -------
    ndarray of shape (n,)
        Probabilities in (0, 1).
    """
    steady = settings.steady_fix_probability
    odds = steady / (1.0 - steady) * np.sqrt(usual_var / stated_var)
    return np.asarray(odds / (1.0 + odds))


def with_restarts(
    bank: TrackBank,
    wild: BoolArray,
    positions: FloatArray,
    covariances: FloatArray,
    settings: TrackerSettings,
) -> Update:
    """The update's outcome, with the tracks that had ``reset_after_wild`` wild fixes in a row
    restarted at their newest fix."""
    restarted = bank.wild >= settings.reset_after_wild
    if np.any(restarted):
        fresh = start_tracks(
            positions[restarted], covariances[restarted], bank.times_s[restarted], settings
        )
        bank = bank.put(restarted, fresh)
    return Update(bank=bank, wild=wild, restarted=restarted)


# E[ln X] for X exponential with mean 1: -Euler's gamma. Half the squared norm of a 2-D
# Gaussian residual of per-axis variance v is v X, so the mean of its logarithm is ln v
# minus this.
_EULER_GAMMA = 0.5772156649015329


def _learned_level(
    level: FloatArray,
    residual: FloatArray,
    posterior_var: FloatArray,
    stated_var: FloatArray,
    rate: FloatArray,
    settings: TrackerSettings,
) -> FloatArray:
    """The tracks' noise levels after one more fix (per-axis variance, m^2).

    After the update, a fix's residual (fix minus the updated position) has the per-axis
    variance ``level - tr(P+) / 2``, with ``P+`` the updated position's covariance
    (``posterior_var`` is ``tr(P+) / 2``): one more
    sample of the level is half the residual's squared norm (bias-corrected for the log,
    at most the gate's worth under the stated variance: a fix that says it is wide, as a
    shadowed LED makes it, does not raise the level beyond its word) plus ``tr(P+) / 2``.
    Samples are averaged on a log scale (one wild fix does not undo many steady ones) with a
    memory of ``noise_memory_s``. A filter's ``P+`` errs on the wide side, and so does the
    level: a fix is never trusted beyond what the track has seen."""
    most = 0.5 * settings.gate_chi2 * stated_var
    seen = np.clip(0.5 * np.einsum("na,na->n", residual, residual), 1e-12, most)
    sample = seen * np.exp(_EULER_GAMMA) + posterior_var
    learned = np.exp(np.log(level) + rate * (np.log(sample) - np.log(level)))
    return np.asarray(np.maximum(learned, settings.min_measurement_sd_m**2))


def _memory_rate(elapsed_s: FloatArray | None, count: int, settings: TrackerSettings) -> FloatArray:
    """The weight of a new fix in the learned levels: ``1 - exp(-dt / noise_memory_s)``
    (``dt``: time since the track's previous fix; unknown: one fix in ``e``)."""
    if elapsed_s is None:
        return np.full(count, -np.expm1(-1.0))
    return np.asarray(-np.expm1(-np.maximum(elapsed_s, 0.0) / settings.noise_memory_s))


def estimates(bank: TrackBank) -> tuple[FloatArray, FloatArray]:
    """What each track says: the mixture's mean ``(n, 4)`` and covariance ``(n, 4, 4)`` with,
    on the position, the error successive fixes share (``stated_var - noise_var`` per axis,
    at least 0): a filter averages the noise of its fixes, not an error they all carry, as a
    layout that does not fit the room gives."""
    mean, covariance = combined(bank)
    shared = np.maximum(np.nan_to_num(bank.stated_var - bank.noise_var), 0.0)
    covariance[:, 0, 0] += shared
    covariance[:, 1, 1] += shared
    return mean, covariance


def _model_updates(
    predicted: TrackBank, positions: FloatArray, noises: FloatArray, steady: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each model's Kalman update under both noise hypotheses ``noises`` ``(n, 2, 2, 2)``
    (steady, wide; ``steady`` ``(n,)``: the first one's prior probability), collapsed by their
    likelihoods, and the models' new probabilities.

    Written out for 2 x 2 innovation covariances. Both hypotheses share ``P H^T`` (columns
    ``c0, c1``), so the collapse is taken on the 2 x 2 pieces first: the mixture's mean is
    ``x + c0 E[u0] + c1 E[u1]`` (``u = S^-1 nu``), its covariance ``P - E[K] H P`` plus the
    hypotheses' spread ``w0 w1 d d^T``."""
    prior = predicted.covariances  # (n, m, 4, 4)
    state = predicted.means  # (n, m, 4)
    c0, c1 = prior[..., :, 0], prior[..., :, 1]  # columns of P H^T, (n, m, 4)
    noise = noises[:, None]  # (n, 1, h, 2, 2)
    a = prior[..., 0, 0, None] + noise[..., 0, 0]  # S = H P H^T + R, (n, m, h)
    b = prior[..., 0, 1, None] + noise[..., 0, 1]
    d = prior[..., 1, 1, None] + noise[..., 1, 1]
    det = a * d - b * b
    nu0 = positions[:, None, None, 0] - state[..., 0, None]
    nu1 = positions[:, None, None, 1] - state[..., 1, None]
    u0 = (d * nu0 - b * nu1) / det
    u1 = (a * nu1 - b * nu0) / det
    log_likelihood = -0.5 * (nu0 * u0 + nu1 * u1) - 0.5 * np.log(det)
    log_likelihood += np.stack((np.log(steady), np.log1p(-steady)), axis=-1)[:, None, :]
    # Within each model: the hypotheses' weights; across: the models' (log-sum-exp).
    top = log_likelihood.max(axis=2, keepdims=True)
    weight = np.exp(log_likelihood - top)  # (n, m, h)
    per_model = weight.sum(axis=2)
    within = weight / per_model[:, :, None]
    log_model = np.log(per_model) + top[:, :, 0]
    log_model += np.log(np.maximum(predicted.model_probabilities, 1e-300))
    model_weight = np.exp(log_model - log_model.max(axis=1, keepdims=True))
    probabilities = model_weight / model_weight.sum(axis=1, keepdims=True)
    # E[S^-1] entries and E[u] over the hypotheses, (n, m) each.
    inv_a = np.sum(within * d / det, axis=2)
    inv_b = np.sum(within * b / det, axis=2)
    inv_d = np.sum(within * a / det, axis=2)
    mean_u0 = np.sum(within * u0, axis=2)
    mean_u1 = np.sum(within * u1, axis=2)
    mean = state + c0 * mean_u0[..., None] + c1 * mean_u1[..., None]
    k0 = c0 * inv_a[..., None] - c1 * inv_b[..., None]  # E[K] = P H^T E[S^-1]
    k1 = c1 * inv_d[..., None] - c0 * inv_b[..., None]
    apart = c0 * (u0[..., 0] - u0[..., 1])[..., None] + c1 * (u1[..., 0] - u1[..., 1])[..., None]
    spread = within[..., 0] * within[..., 1]
    covariance = (
        prior
        - k0[..., :, None] * c0[..., None, :]
        - k1[..., :, None] * c1[..., None, :]
        + (spread[..., None] * apart)[..., :, None] * apart[..., None, :]
    )
    return mean, covariance, np.maximum(probabilities, 1e-9)
