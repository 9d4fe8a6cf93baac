"""Compiled filter step: :func:`app.vlp.tracking.filter.predict` then
:func:`~app.vlp.tracking.filter.update`, one track at a time.

Its NumPy reference, :func:`~app.vlp.tracking.step.predict_update_reference`, documents the
method (the standing / walking IMM, a fix's two noise hypotheses, the learned noise level);
:func:`~app.vlp.tracking.step.predict_update_kernel` packs its arguments for this one. A
room's step updates every track (100 of them, or 10): NumPy's cost there is the overhead of
some hundred and fifty array calls on arrays of a few hundred numbers, not the arithmetic.
Here each track runs alone in scalars and 4 x 4 blocks. A track's restart after too many wild
fixes is left to the caller (it is rare, and :func:`~app.vlp.tracking.filter.start_tracks` is
the one place that starts a track). Private: callers validate.
"""

from __future__ import annotations

import math

import numpy as np

from .._kernels import compiled
from ..typing import BoolArray, FloatArray, IntArray

__all__ = ["predict_update_kernel"]

# E[ln X] for X exponential with mean 1 (see filter._learned_level).
_EULER_GAMMA = 0.5772156649015329


@compiled
def predict_update_kernel(
    means: FloatArray,
    covariances: FloatArray,
    model_probabilities: FloatArray,
    times_s: FloatArray,
    wild: IntArray,
    noise_var: FloatArray,
    stated_var: FloatArray,
    offset: FloatArray,
    positions: FloatArray,
    fix_covariances: FloatArray,
    time_s: float,
    learn: bool,
    inflate_chi2: FloatArray,
    settings: tuple[float, float, float, float, float, float, float, float, float, float, float],
) -> tuple[
    FloatArray,
    FloatArray,
    FloatArray,
    FloatArray,
    IntArray,
    FloatArray,
    FloatArray,
    FloatArray,
    BoolArray,
]:
    """Every track (row ``k``) predicted to ``time_s`` and updated with fix ``k`` (a fix beyond
    ``inflate_chi2[k]`` inflated to it).

    ``settings``: (walking_accel_sd_mps2, standing_drift_mps, start_speed_sd_mps,
    mean_dwell_s, max_speed_mps, gate_chi2, min_measurement_sd_m, steady_fix_probability,
    noise_memory_s, start_run_sd, start_run_ratio). Returns the new bank's arrays (means,
    covariances, model probabilities, times, wild streaks, noise levels, stated levels,
    offsets) and which fixes were wild.
    """
    accel_sd, drift_sd, start_sd, dwell, max_speed, gate, floor_sd, steady, memory = settings[:9]
    run_sd, run_ratio = settings[9], settings[10]
    n = times_s.shape[0]
    out_means = np.empty((n, 2, 4))
    out_covs = np.empty((n, 2, 4, 4))
    out_probs = np.empty((n, 2))
    out_times = np.empty(n)
    out_wild = np.empty(n, dtype=np.intp)
    out_noise = np.empty(n)
    out_stated = np.empty(n)
    out_offset = np.zeros((n, 2))
    was_wild = np.empty(n, dtype=np.bool_)
    accel = accel_sd * accel_sd
    floor = floor_sd * floor_sd
    steady_odds = steady / (1.0 - steady)
    mixed = np.empty((2, 4))
    mixed_cov = np.empty((2, 4, 4))
    pred = np.empty((2, 4))
    pred_cov = np.empty((2, 4, 4))
    weights = np.empty((2, 2))
    probs = np.empty(2)
    noises = np.empty((2, 3))  # per hypothesis: R00, R01, R11
    log_like = np.empty((2, 2))
    log_model = np.empty(2)
    # each (model, hypothesis)'s whitened innovation S^-1 nu and innovation covariance S:
    # the likelihoods and the update both read them
    u0s = np.empty((2, 2))
    u1s = np.empty((2, 2))
    innovation_cov = np.empty((2, 2, 4))  # S00, S01, S11, det S
    for k in range(n):
        # --- predict (IMM interaction, then each model's motion) ---
        dt = max(time_s - times_s[k], 0.0)
        # --- the fix's offset from the standing model, in sds (starts.whitened_offsets) ---
        fix_var = (fix_covariances[k, 0, 0] + fix_covariances[k, 1, 1]) / 2.0 + floor
        level = noise_var[k] if math.isfinite(noise_var[k]) else fix_var
        spread_var = (covariances[k, 0, 0, 0] + covariances[k, 0, 1, 1]) / 2.0
        offset_sd = math.sqrt(level + spread_var + drift_sd * drift_sd * dt)
        off0 = (positions[k, 0] - means[k, 0, 0]) / offset_sd
        off1 = (positions[k, 1] - means[k, 0, 1]) / offset_sd
        previous = math.hypot(offset[k, 0], offset[k, 1])
        along = (offset[k, 0] * off0 + offset[k, 1] * off1) / max(previous, 1e-12)
        run = (
            learn and model_probabilities[k, 0] >= 0.5 and previous >= run_sd and along >= previous
        )
        switch = -math.expm1(-dt / dwell)
        for j in range(2):
            total = 0.0
            for i in range(2):
                w = model_probabilities[k, i] * ((1.0 - switch) if i == j else switch)
                weights[i, j] = w
                total += w
            probs[j] = total
            for i in range(2):
                weights[i, j] /= total
        for j in range(2):
            for a in range(4):
                mixed[j, a] = weights[0, j] * means[k, 0, a] + weights[1, j] * means[k, 1, a]
            for a in range(4):
                for b in range(4):
                    value = 0.0
                    for i in range(2):
                        value += weights[i, j] * covariances[k, i, a, b]
                    for i in range(2):
                        value += (
                            weights[i, j]
                            * (means[k, i, a] - mixed[j, a])
                            * (means[k, i, b] - mixed[j, b])
                        )
                    mixed_cov[j, a, b] = value
        # Standing: the position stays, the velocity is the noise alone.
        pred[0, 0], pred[0, 1], pred[0, 2], pred[0, 3] = mixed[0, 0], mixed[0, 1], 0.0, 0.0
        pred_cov[0, :, :] = 0.0
        pred_cov[0, 0, 0] = mixed_cov[0, 0, 0] + drift_sd * drift_sd * dt
        pred_cov[0, 0, 1] = mixed_cov[0, 0, 1]
        pred_cov[0, 1, 0] = mixed_cov[0, 1, 0]
        pred_cov[0, 1, 1] = mixed_cov[0, 1, 1] + drift_sd * drift_sd * dt
        pred_cov[0, 2, 2] = pred_cov[0, 3, 3] = start_sd * start_sd
        # Walking: constant velocity, white-noise acceleration.
        for a in range(2):
            pred[1, a] = mixed[1, a] + dt * mixed[1, a + 2]
            pred[1, a + 2] = mixed[1, a + 2]
        for a in range(2):
            for b in range(2):
                pp = mixed_cov[1, a, b]
                pv = mixed_cov[1, a, b + 2]
                vp = mixed_cov[1, a + 2, b]
                vv = mixed_cov[1, a + 2, b + 2]
                pred_cov[1, a, b] = pp + dt * (pv + vp) + (dt * dt) * vv
                pred_cov[1, a, b + 2] = pv + dt * vv
                pred_cov[1, a + 2, b] = vp + dt * vv
                pred_cov[1, a + 2, b + 2] = vv
        for a in range(2):
            pred_cov[1, a, a] += accel * dt**3 / 3.0
            pred_cov[1, a, a + 2] += accel * dt**2 / 2.0
            pred_cov[1, a + 2, a] += accel * dt**2 / 2.0
            pred_cov[1, a + 2, a + 2] += accel * dt
        for m in range(2):
            _cap_speed(pred, m, max_speed)
        out_times[k] = max(time_s, times_s[k])
        # --- update: the gate on the mixture taken as one Gaussian ---
        mean0 = probs[0] * pred[0, 0] + probs[1] * pred[1, 0]
        mean1 = probs[0] * pred[0, 1] + probs[1] * pred[1, 1]
        p00 = p01 = p11 = 0.0
        for m in range(2):
            s0, s1 = pred[m, 0] - mean0, pred[m, 1] - mean1
            p00 += probs[m] * (pred_cov[m, 0, 0] + s0 * s0)
            p01 += probs[m] * (pred_cov[m, 0, 1] + s0 * s1)
            p11 += probs[m] * (pred_cov[m, 1, 1] + s1 * s1)
        r00 = fix_covariances[k, 0, 0] + floor
        r01 = fix_covariances[k, 0, 1]
        r11 = fix_covariances[k, 1, 1] + floor
        z0, z1 = positions[k, 0], positions[k, 1]
        nu0, nu1 = z0 - mean0, z1 - mean1
        wa, wb, wd = p00 + r00, p01 + r01, p11 + r11
        distance2 = (wd * nu0 * nu0 - 2.0 * wb * nu0 * nu1 + wa * nu1 * nu1) / (wa * wd - wb * wb)
        is_wild = distance2 > gate
        was_wild[k] = is_wild
        if distance2 > inflate_chi2[k]:
            scale = distance2 / inflate_chi2[k]
            noises[1, 0] = scale * wa - p00
            noises[1, 1] = scale * wb - p01
            noises[1, 2] = scale * wd - p11
        else:
            noises[1, 0], noises[1, 1], noises[1, 2] = r00, r01, r11
        shrink = min(1.0, level / fix_var) if learn else 1.0
        noises[0, 0], noises[0, 1], noises[0, 2] = r00 * shrink, r01 * shrink, r11 * shrink
        # the steady hypothesis's prior (filter.steady_probabilities; even odds for a fix
        # that may be another terminal's)
        before = stated_var[k] if math.isfinite(stated_var[k]) else fix_var
        odds = steady_odds * math.sqrt(before / fix_var) if learn else 1.0
        log_hypothesis = (math.log(odds / (1.0 + odds)), math.log(1.0 / (1.0 + odds)))
        # --- each model's update under both hypotheses, collapsed ---
        for m in range(2):
            for h in range(2):
                a_ = pred_cov[m, 0, 0] + noises[h, 0]
                b_ = pred_cov[m, 0, 1] + noises[h, 1]
                d_ = pred_cov[m, 1, 1] + noises[h, 2]
                det = a_ * d_ - b_ * b_
                n0, n1 = z0 - pred[m, 0], z1 - pred[m, 1]
                u0 = (d_ * n0 - b_ * n1) / det
                u1 = (a_ * n1 - b_ * n0) / det
                u0s[m, h], u1s[m, h] = u0, u1
                innovation_cov[m, h, 0], innovation_cov[m, h, 1] = a_, b_
                innovation_cov[m, h, 2], innovation_cov[m, h, 3] = d_, det
                log_like[m, h] = (
                    -0.5 * (n0 * u0 + n1 * u1) - 0.5 * math.log(det) + log_hypothesis[h]
                )
        for m in range(2):
            top = max(log_like[m, 0], log_like[m, 1])
            per_model = math.exp(log_like[m, 0] - top) + math.exp(log_like[m, 1] - top)
            log_model[m] = math.log(per_model) + top + math.log(max(probs[m], 1e-300))
        best = max(log_model[0], log_model[1])
        e0, e1 = math.exp(log_model[0] - best), math.exp(log_model[1] - best)
        new_probs = (max(e0 / (e0 + e1), 1e-9), max(e1 / (e0 + e1), 1e-9))
        for m in range(2):
            top = max(log_like[m, 0], log_like[m, 1])
            w0 = math.exp(log_like[m, 0] - top)
            w1 = math.exp(log_like[m, 1] - top)
            within0, within1 = w0 / (w0 + w1), w1 / (w0 + w1)
            inv_a = inv_b = inv_d = mean_u0 = mean_u1 = 0.0
            for h in range(2):
                a_, b_ = innovation_cov[m, h, 0], innovation_cov[m, h, 1]
                d_, det = innovation_cov[m, h, 2], innovation_cov[m, h, 3]
                within = within0 if h == 0 else within1
                inv_a += within * d_ / det
                inv_b += within * b_ / det
                inv_d += within * a_ / det
                mean_u0 += within * u0s[m, h]
                mean_u1 += within * u1s[m, h]
            spread = within0 * within1
            du0, du1 = u0s[m, 0] - u0s[m, 1], u1s[m, 0] - u1s[m, 1]
            for a in range(4):
                c0a, c1a = pred_cov[m, a, 0], pred_cov[m, a, 1]
                out_means[k, m, a] = pred[m, a] + c0a * mean_u0 + c1a * mean_u1
                k0 = c0a * inv_a - c1a * inv_b
                k1 = c1a * inv_d - c0a * inv_b
                apart_a = c0a * du0 + c1a * du1
                for b in range(4):
                    c0b, c1b = pred_cov[m, b, 0], pred_cov[m, b, 1]
                    apart_b = c0b * du0 + c1b * du1
                    out_covs[k, m, a, b] = (
                        pred_cov[m, a, b] - k0 * c0b - k1 * c1b + spread * apart_a * apart_b
                    )
            out_probs[k, m] = new_probs[m]
        # --- the learned levels ---
        rate = -math.expm1(-dt / memory)
        stated_level = 1.0 / (1.0 / before + rate * (1.0 / fix_var - 1.0 / before))
        out_stated[k] = stated_level
        if learn:
            x0 = new_probs[0] * out_means[k, 0, 0] + new_probs[1] * out_means[k, 1, 0]
            x1 = new_probs[0] * out_means[k, 0, 1] + new_probs[1] * out_means[k, 1, 1]
            posterior = 0.0
            for m in range(2):
                g0, g1 = out_means[k, m, 0] - x0, out_means[k, m, 1] - x1
                posterior += new_probs[m] * (
                    out_covs[k, m, 0, 0] + out_covs[k, m, 1, 1] + g0 * g0 + g1 * g1
                )
            posterior /= 2.0
            r0, r1 = z0 - x0, z1 - x1
            most = 0.5 * gate * fix_var
            seen = min(max(0.5 * (r0 * r0 + r1 * r1), 1e-12), most)
            sample = seen * math.exp(_EULER_GAMMA) + posterior
            learned = math.exp(math.log(level) + rate * (math.log(sample) - math.log(level)))
            out_noise[k] = max(learned, floor_sd * floor_sd)
        else:
            out_noise[k] = stated_level
        out_wild[k] = wild[k] + 1 if is_wild else 0
        for m in range(2):
            _cap_speed_row(out_means, k, m, max_speed)
        # --- a consistent run ends a standing track's stand (starts.after_runs) ---
        if learn:
            out_offset[k, 0], out_offset[k, 1] = off0, off1
            if run:
                walking = out_probs[k, 1]
                odds = run_ratio * walking
                total = 1.0 - walking + odds
                out_probs[k, 0] = max((1.0 - walking) / total, 1e-9)
                out_probs[k, 1] = max(odds / total, 1e-9)
    return (
        out_means,
        out_covs,
        out_probs,
        out_times,
        out_wild,
        out_noise,
        out_stated,
        out_offset,
        was_wild,
    )


@compiled
def _cap_speed(means: FloatArray, model: int, max_speed: float) -> None:
    speed = math.hypot(means[model, 2], means[model, 3])
    factor = min(1.0, max_speed / max(speed, 1e-12))
    means[model, 2] *= factor
    means[model, 3] *= factor


@compiled
def _cap_speed_row(means: FloatArray, row: int, model: int, max_speed: float) -> None:
    speed = math.hypot(means[row, model, 2], means[row, model, 3])
    factor = min(1.0, max_speed / max(speed, 1e-12))
    means[row, model, 2] *= factor
    means[row, model, 3] *= factor
