"""What an answer of the default solver reports beyond its fit (docs/explanation/solver.md,
"Report"): each estimate's far optima (:func:`aggregated_far_optima`,
:func:`terminal_far_optima`) and mirror twins held in its radius, radii bounded by the
floor's diagonal (:func:`reported`), and every sentence of ``fit.detail`` the solver adds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..._kernels import dispatch
from ...ambiguity import (
    covering_twins,
    far_optima,
    farthest_in_region,
    mirror_twins,
)
from ...radii import bounded_covariances
from ...typing import FloatArray
from ...uncertainty import FitQuality
from ._compiled import scores as compiled_scores
from .fitting import (
    Run,
    grid_correlations,
    whitened_residual,
)
from .room import PreparedRoom
from .state import FitState
from .tolerances import ToleranceFit
from .whitening import (
    Whitening,
    target_gains,
)
from .whitening_memo import state_key

NO_FIT_TEST = (
    "the power model cannot tell its noise from its signal, so its chi-square is no test of "
    "the model (the 95 % radii use the scatter of its residuals); send the correlation "
    "matrix or each terminal's amplitudes for one"
)


def reported(
    room: PreparedRoom,
    positions: FloatArray,
    covariances: FloatArray,
    fit: FitQuality,
    far: FloatArray,
) -> tuple[FloatArray, FitQuality]:
    """The covariances (K, 2, 2) and fit quality an answer reports: each estimate's
    region widened to hold its mirror twin (:mod:`app.vlp.ambiguity`: LEDs on one line
    give the same gains on both sides) or its ``far`` optimum (shape (K, 2), NaN where
    none; :func:`terminal_far_optima`, :func:`aggregated_far_optima`), the farther of the two,
    the fit's detail saying so, and no 95 % radius beyond the floor's diagonal
    (:func:`app.vlp.radii.bounded_covariances`)."""
    floor = room.fingerprint.layout.room
    diagonal = math.hypot(floor.length, floor.width)
    has_far = np.isfinite(far[:, 0])
    if not room.twins_possible and not has_far.any():
        return bounded_covariances(covariances, diagonal), fit  # nothing to widen
    twins = (
        mirror_twins(positions, room.led_xy, room.gains_at, (floor.length, floor.width))
        if room.twins_possible
        else np.full_like(positions, np.nan)
    )
    has_twin = np.isfinite(twins[:, 0])
    if has_far.any():
        # One widening per estimate, to the farther point: the far optimum when the
        # twin is nearer or none.
        to_twin = np.linalg.norm(twins - positions, axis=1)
        to_far = np.linalg.norm(far - positions, axis=1)
        has_far &= ~(has_twin & (to_twin > to_far))
        has_twin &= ~has_far
        twins = np.where(has_far[:, np.newaxis], far, twins)
    if has_twin.any() or has_far.any():
        covariances = covering_twins(covariances, positions, twins)
    detail = fit.detail
    if has_far.any():
        detail += (
            f"; {int(has_far.sum())} of the estimates would fit the measurement about "
            "as well at another place beyond their radius: their radii hold it"
        )
    if has_twin.any():
        detail += (
            f"; {int(has_twin.sum())} of the estimates see LEDs on one line and have a "
            "mirror image across it that receives the same signals: their radii hold both "
            "(LEDs off that line would tell them apart)"
        )
    if detail != fit.detail:
        fit = replace(fit, detail=detail)
    return bounded_covariances(covariances, diagonal), fit


def terminal_far_optima(
    room: PreparedRoom,
    values: FloatArray,
    positions: FloatArray,
    covariances: FloatArray,
    sigma2: float,
    led_weights: FloatArray | None = None,
    gain_sd: float | None = None,
) -> FloatArray:
    """Each terminal's farthest other optimum of its own amplitudes beyond its radius
    (:func:`app.vlp.ambiguity.far_optima`: a grid point that explains them as well, e.g.
    a receiver in a dark corner, or on either side of a row of LEDs), shape (K, 2), NaN
    where none. Dense rooms whose gains are small enough to scan per answer (else all
    NaN). ``led_weights`` (M,): each amplitude's whitening weight, shared by the terminals
    (None: one weight, ``sigma2`` the noise variance). ``gain_sd``: the standard deviation
    of a prior on each place's gain (None: free)."""
    if not room.scans_profiles:
        return np.full_like(positions, np.nan)
    if led_weights is not None:
        return far_optima(
            values * led_weights,
            room.gains * led_weights[:, np.newaxis],
            room.centres,
            positions,
            covariances,
            sigma2,
            room.fingerprint.layout.grid.step,
            gain_sd=gain_sd,
        )
    return far_optima(
        values,
        room.gains,
        room.centres,
        positions,
        covariances,
        sigma2,
        room.fingerprint.layout.grid.step,
        room.column_energy,
        gain_sd=gain_sd,
    )


def aggregated_far_optima(
    room: PreparedRoom, run: Run, state: FitState, covariances: FloatArray
) -> FloatArray:
    """Each estimate's farthest other optimum of the aggregated measurement beyond its
    radius, shape (K, 2), NaN where none: the estimate moved over the grid with the
    others held, its gain free (:func:`profiles`), and the region where that profile
    is within chi-square(2)'s 95 % of its best
    (:func:`app.vlp.ambiguity.farthest_in_region`). It finds what the covariance, a
    curvature at one optimum, cannot: a receiver in the dark, the other side of a row of
    LEDs, a spot that another target's light also explains. Dense rooms whose gains are
    small enough to scan per answer (else all NaN)."""
    k = state.n_targets
    if not room.scans_profiles or k == 0:
        return np.full((k, 2), np.nan)
    explained, best = profiles(room, run, state)
    return farthest_in_region(
        explained,
        best,
        room.centres,
        state.positions,
        covariances,
        room.fingerprint.layout.grid.step,
    )


def profiles(room: PreparedRoom, run: Run, state: FitState) -> tuple[FloatArray, FloatArray]:
    """How much of the whitened cost each estimate would explain at every grid point,
    the others held and its gain free, shape (K, N), and how much it explains where it
    is, shape (K,) (dense rooms, the final whitened metric).

    Without estimate k the whitened residual is ``r_k = r + w_k a_k`` (``a_k`` its
    whitened atom, ``w_k`` its effective weight); a unit atom ``a_j`` at grid point j
    with its gain free explains ``max(<a_j, r_k>, 0)^2 / ||a_j||^2``, and the estimate
    itself ``||r_k||^2 - ||r||^2``. In the rotated basis (``rho = U^T g``) every inner
    product of atoms is a quadratic form in ``rho_j o rho_k`` with the squared weights,
    so all K profiles cost one pass over the grid each, without forming any ``r_k``
    (:func:`correlation_profiles_kernel`, or its NumPy reference
    :func:`correlation_profiles_reference`). Kept per run, state values and priors.
    """
    key = (state_key(state), run.priors)
    known = run.profiles.get(key)
    if known is None:
        known = run.profiles[key] = computed_profiles(room, run, state)
    return known


def computed_profiles(
    room: PreparedRoom, run: Run, state: FitState
) -> tuple[FloatArray, FloatArray]:
    """:func:`profiles`, computed."""
    white, residual = whitened_residual(room, run, state)
    weights = white.weights
    targets = target_gains(room.kernel, state)  # (M, K)
    multipliers = state.effective_weights()
    if room.model == "power":
        # The insertion scores' inner products (exact for power), and the cross terms.
        num, norms = grid_correlations(room, white, residual)
        squared = weights**2
        target_sq = targets**2
        cross = (target_sq * squared[:, np.newaxis]).T @ room.gains_sq  # (K, N)
        without = num[np.newaxis, :] + multipliers[:, np.newaxis] * cross
        own_num = (weights * residual) @ target_sq
        own_norm = squared @ target_sq**2
        return explained_profiles(without, norms, own_num, own_norm, multipliers)
    return dispatch(correlation_profiles_kernel, correlation_profiles_reference)(
        white, residual, room.gains, targets, multipliers
    )


def explained_profiles(
    without: FloatArray,
    norms: FloatArray,
    own_num: FloatArray,
    own_norm: FloatArray,
    multipliers: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`profiles` from the inner products ``<a_j, r_k>`` (K, N), ``||a_j||^2`` (N,),
    ``<a_k, r>`` and ``||a_k||^2`` (K,): what each estimate explains at every grid point,
    and at its best."""
    explained = np.maximum(without, 0.0) ** 2 / np.maximum(norms, 1e-300)
    own = 2.0 * multipliers * own_num + multipliers**2 * own_norm
    return explained, np.maximum(explained.max(axis=1), own)


def correlation_profiles_kernel(
    white: Whitening,
    residual: FloatArray,
    gains: FloatArray,
    targets: FloatArray,
    multipliers: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`correlation_profiles_reference` in one compiled call."""
    explained, best = compiled_scores.correlation_profiles_kernel(
        white.compiled(),
        np.ascontiguousarray(residual, dtype=np.float64),
        gains,
        np.ascontiguousarray(targets, dtype=np.float64),
        np.ascontiguousarray(multipliers, dtype=np.float64),
    )
    return explained, best


def correlation_profiles_reference(
    white: Whitening,
    residual: FloatArray,
    gains: FloatArray,
    targets: FloatArray,
    multipliers: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`profiles` of the correlation model in NumPy: the inner products of the
    estimates' and the grid's whitened atoms (:func:`explained_profiles`'s), from the
    rotated gains."""
    weights = white.weights
    n_leds = gains.shape[0]
    # Symmetric M x M forms of the whitened entries (each off-diagonal entry split
    # over its two places): r's, and the squared weights'.
    quadratic = np.zeros((n_leds, n_leds))
    quadratic[white.upper, white.lower] = 0.5 * weights * residual
    quadratic = quadratic + quadratic.T
    squared = np.zeros((n_leds, n_leds))
    squared[white.upper, white.lower] = 0.5 * weights**2
    squared = squared + squared.T
    grid = white.rotate(gains)  # (M, N)
    rotated = white.rotate(targets)  # (M, K)
    # r_k's form: r's plus w_k times the squared weights on rho_k rho_k^T.
    forms = quadratic + multipliers[:, np.newaxis, np.newaxis] * squared * (
        rotated.T[:, :, np.newaxis] * rotated.T[:, np.newaxis, :]
    )
    without = np.sum(np.matmul(forms, grid) * grid, axis=1)  # (K, N)
    grid_sq = grid * grid
    norms = np.sum((squared @ grid_sq) * grid_sq, axis=0)
    own_num = np.sum((quadratic @ rotated) * rotated, axis=0)
    rotated_sq = rotated * rotated
    own_norm = np.sum((squared @ rotated_sq) * rotated_sq, axis=0)
    return explained_profiles(without, norms, own_num, own_norm, multipliers)


def aggregated_fit_detail(
    room: PreparedRoom,
    fit: FitQuality,
    tolerances: ToleranceFit | None,
    n_values: int,
    n_targets: int,
) -> FitQuality:
    """The fit quality of an aggregated answer with its sentences: the room's tolerances
    when fitted, no goodness-of-fit test where the noise is not identified (power model),
    and a poor fit where ``n_values`` cannot determine ``n_targets`` and the noise."""
    if tolerances is not None:
        amplitude_rms = float(np.sqrt(np.mean(np.expm1(tolerances.led_log_amplitudes) ** 2)))
        angle_rms = float(np.sqrt(np.mean(tolerances.led_half_power_changes_deg**2)))
        tilts = (
            ""
            if tolerances.tilts is None
            else ", and the photodiodes' tilts "
            f"({math.degrees(float(np.sqrt(np.mean(tolerances.tilts**2)))):.1f} deg rms "
            "per component)"
        )
        fit = replace(
            fit,
            detail=f"{fit.detail}; the LEDs' tolerances were fitted (amplitudes "
            f"{100 * amplitude_rms:.1f} % and half-power angles {angle_rms:.1f} deg rms "
            f"from the layout){tilts}: a survey calibration would measure the LEDs once",
        )
    if not room.noise_identified and fit.quality != "scale_mismatch":
        # No noise level to hold the residuals against: no goodness-of-fit test.
        fit = replace(fit, quality="ok", detail=NO_FIT_TEST)
    unknowns = 2 * n_targets + 1
    if n_values < unknowns and fit.quality != "scale_mismatch":
        fit = replace(
            fit,
            quality="poor",
            detail=f"{n_values} values cannot determine {n_targets} targets "
            f"and the noise ({unknowns} unknowns): other placements fit them as well; "
            "send the correlation matrix or each terminal's amplitudes",
        )
    return fit
