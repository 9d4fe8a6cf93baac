"""Terminals that send their own amplitudes (docs/explanation/solver.md, "Terminals"): each
located by its own fit (:func:`.terminals.fit_terminal`), the noise and the model errors'
variances pooled over all of them, the LEDs' errors weighted in when they explain a
significant share of the residuals, and the answer's radii and sentences.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from scipy import special

from ..._kernels import dispatch
from ...scale import check_amplitude_scale
from ...typing import FloatArray, IntArray
from ...uncertainty import (
    FITS_TO_NOISE,
    Misfit,
    MisfitDesign,
    assess_fit,
    fit_misfit,
    own_excess_widening,
    predictive_covariances,
)
from .._censored import censored_substitutes, with_censored_variance
from ..base import Solution
from ._compiled import starts as compiled_starts
from .lm import whitening_weight
from .report import (
    reported,
    terminal_far_optima,
)
from .room import PreparedRoom
from .terminal_weights import (
    measured_misfit,
    measured_variances,
    own_variances_estimable,
    rewhitened,
    scatter_explains,
    tail_weighted_variances,
    terminal_nll,
)
from .terminals import TerminalFit, fit_terminal, starting_cells
from .uncertainty import (
    estimable_misfit,
    misfit_design,
    response_covariances,
    shape_gradients,
)

# Share of the terminals' residual sum of squares that the LEDs' relative errors must
# explain, in standard deviations of the noise's chi-square, for the terminals to be
# refitted with the LEDs' errors in their weights.
_LED_WEIGHT_SIGNIFICANCE = 3.0
# ... and, pooled over several terminals, the largest relative sd of an LED's error taken for
# one: data sheets bin flux within +-10-15 %; a larger pooled estimate is one terminal's fit
# that does not hold (placed far off in a badly lit room), and the weights would move the
# others off. A lone terminal's estimate weights only itself: on beams far from their
# nominal shape it is large and real (docs/decisions/led-errors-in-terminal-weights.md).
_MAX_LED_ERROR_SD = 0.25
# A refit whose weights were taken at its start is a walk-off, and the start is kept, when it
# leaves the amplitudes less likely than the start did by more than half this quantile of a
# chi-square on all of them (on a measured survey, such fits went metres off; within the
# quantile, a refit's small losses are kept: holding them back cost the eleven-luminaire
# lobby accuracy).
_WALK_OFF_PROBABILITY = 0.999
# Reweightings of a terminal fitted with a Student-t scatter: its weights settle within a few.
_TAIL_REWEIGHTS = 3
# Grid cells a weighted pass starts from besides the previous pass's optimum (the best of
# that pass's own cost, :func:`profile_starts`), and how far apart they are, metres: the
# first pass's equal weights and free gain can have led its few starts all into one wrong
# basin, which with few LEDs detected is far from the truth.
_PROFILE_STARTS = 3
_PROFILE_START_SPACING_M = 0.5


def solve_terminals(
    room: PreparedRoom,
    amplitudes: FloatArray,
    heights: FloatArray | None = None,
    normals: FloatArray | None = None,
    floors: FloatArray | None = None,
) -> Solution:
    """Locate each terminal from its own amplitudes; estimate k belongs to terminal k.

    Parameters
    ----------
    amplitudes : ndarray of shape (K, M)
        Each terminal's received pilot amplitudes (validated by the caller); NaN where
        the LED was not detected (censored below the terminal's floor: :mod:`._censored`).
    heights : ndarray of shape (K,) or None, metres
        Terminals' own heights; NaN (or None for all) where unknown.
    normals : ndarray of shape (K, 3) or None
        Terminals' photodiode unit normals; None for straight up.
    floors : ndarray of shape (K,) or None
        Terminals' detection floors (amplitude units); NaN (or None for all): the
        weakest amplitude each detected.

    Notes
    -----
    See :mod:`.gridless.terminals`. Two passes: without priors, to estimate the amplitude
    noise variance pooled over the terminals (its residual sum of squares over its
    degrees of freedom), then with the gain and height priors weighted by it, started from
    the first pass's optimum and from the grid cells where this cost is lowest
    (:func:`profile_starts`) (each terminal's gain held at 1 and its photodiode level
    unless freeing them lowers the cost significantly, or its tilt fitted with the layout's
    ``receiver_tilt_sd`` as the prior when it declares one: :func:`.terminals.fit_terminal`).
    The covariance of each position is the sandwich of its whitened fit with the noise and
    the model errors the fit does not fit (:func:`terminal_misfit_columns`), their
    variances estimated from all terminals' residuals together (the first pass's noise
    level holds part of the misfit, so the noise variance is re-estimated with them)
    and widened for their degrees of freedom (:mod:`app.vlp.uncertainty`). When the
    LEDs' relative errors explain a significant share of the residuals
    (:func:`_led_errors_seen`; option ``terminal_led_weights``), a third pass refits each
    terminal with each amplitude's variance the noise's plus that error's, and the
    variances are estimated again from its residuals. In a survey-calibrated room the third
    pass weights each amplitude by the survey's measured scatter instead
    (:func:`measured_variances`); when the layout says the receivers are level or the scatter
    explains the request's residuals (:func:`scatter_explains`) the covariances rest on the
    survey's degrees of freedom, else the terminals keep that pass's positions and the
    covariances of the passes above.
    """
    # [censored hook] LEDs not detected enter as their interval below the floor.
    amplitudes, censored_var = censored_substitutes(
        np.asarray(amplitudes, dtype=np.float64), floors
    )
    check_amplitude_scale(room.fingerprint, amplitudes)
    values = amplitudes / room.scale
    censored_var = censored_var / room.scale**2
    n_terminals, n_leds = values.shape
    windows = room.windows
    if windows is None:
        if room.dense:
            correlations = values @ room.gains
        else:
            correlations = np.asarray((room.gains_sparse.T @ values.T).T)
        scores = np.where(correlations > 0.0, correlations**2 / room.column_energy, 0.0)
    spacing = 2.0 * room.fingerprint.layout.grid.step
    own_heights = [
        None if heights is None or not np.isfinite(heights[k]) else float(heights[k])
        for k in range(n_terminals)
    ]
    own_normals = [None if normals is None else normals[k] for k in range(n_terminals)]
    # The layout's tilt spread, when it declares one, is each unknown tilt's prior; a
    # layout whose photodiodes are level has no tilt to fit.
    declared_tilt_sd = math.radians(room.fingerprint.layout.grid.receiver_tilt_sd)
    tilt_spread_known = room.options.tilt_sd is not None and declared_tilt_sd > 0
    tilt_sd = declared_tilt_sd if tilt_spread_known else room.options.tilt_sd
    if room.receivers_level:
        tilt_sd = None
    first = []
    for k in range(n_terminals):
        kernel, seen, unseen_energy = room.kernel, values[k], 0.0
        if windows is None:
            cells = starting_cells(scores[k], room.centres, spacing)
        else:
            # Large rooms: the first pass (starts and the noise estimate) fits the LEDs
            # near the terminal; the second pass below fits all of them.
            cells = windows.starting_cells(values[k], room.centres, spacing)
            kernel, inside = windows.near_kernel(values[k], room.scale)
            seen = values[k][inside]
            unseen_energy = float(values[k] @ values[k] - seen @ seen)
        fit = fit_terminal(
            kernel,
            seen,
            room.centres[cells],
            priors=room.priors,
            sigma2=None,
            height=own_heights[k],
            normal=own_normals[k],
            tilt_sd=tilt_sd,
            tilt_spread_known=tilt_spread_known,
        )
        first.append(replace(fit, rss=fit.rss + unseen_energy))
    dof = np.array([max(n_leds - fit.n_params, 1) for fit in first])
    sigma2 = sum(fit.rss for fit in first) / float(dof.sum())

    def refitted(
        starts: list[TerminalFit],
        variances: Callable[[TerminalFit], float | FloatArray],
        search: bool,
        likelihood: Callable[[TerminalFit], FloatArray] | None = None,
        tail_dof: float | None = None,
    ) -> list[TerminalFit]:
        """Every terminal fitted on all the LEDs from ``starts`` (and, with ``search``, from
        the best grid cells of its new cost), its amplitudes weighted by ``variances`` of its
        start (plus, where censored, their interval's own).

        With ``likelihood`` (the amplitudes' variances at a fit, as ``variances``), a
        terminal keeps its start, whitened as the new fit would be, where the new fit is less
        likely than its start by more than chance would make it
        (:func:`terminal_nll` with ``tail_dof``; :data:`_WALK_OFF_PROBABILITY`): weights
        taken at the start are not the variances elsewhere, and under them a fit can walk
        from its start to a place whose own variances explain the amplitudes far worse."""
        weights = [
            with_censored_variance(variances(start), censored_var[k])  # [censored hook]
            for k, start in enumerate(starts)
        ]
        previous = np.array([start.position for start in starts]).reshape(-1, 2)
        extra = (
            profile_starts(room, values, weights, previous)
            if search
            else [np.empty((0, 2))] * len(starts)
        )
        fitted = [
            fit_terminal(
                room.kernel,
                values[k],
                np.vstack((previous[k : k + 1], extra[k])),
                priors=room.priors,
                sigma2=weights[k],
                height=own_heights[k],
                normal=own_normals[k],
                tilt_sd=tilt_sd,
                tilt_spread_known=tilt_spread_known,
            )
            for k in range(len(starts))
        ]
        if likelihood is None:
            return fitted
        walk_off = 0.5 * float(special.chdtri(n_leds, 1.0 - _WALK_OFF_PROBABILITY))

        def nll(k: int, fit: TerminalFit) -> float:
            own = with_censored_variance(likelihood(fit), censored_var[k])
            # floored as the fits' own weights are (a variance of 0 has no likelihood)
            weight = whitening_weight(values[k], np.broadcast_to(own, (n_leds,)).copy())
            return terminal_nll(fit, np.broadcast_to(1.0 / weight**2, (n_leds,)), tail_dof)

        return [
            new
            if nll(k, new) <= nll(k, start) + walk_off
            else rewhitened(start, whitening_weight(values[k], weights[k]))
            for k, (start, new) in enumerate(zip(starts, fitted, strict=True))
        ]

    fits = refitted(first, lambda _: sigma2, search=room.options.weighted_pass_starts)

    def misfit_of(
        fits: list[TerminalFit], led_errors: bool = True
    ) -> tuple[list[MisfitDesign], Misfit]:
        designs = [
            misfit_design(
                fit.jacobian,
                fit.normal,
                terminal_misfit_columns(
                    room, fit, own_heights[k] is not None, own_normals[k] is not None, led_errors
                ),
            )
            for k, fit in enumerate(fits)
        ]
        return designs, fit_misfit(designs, [fit.residual for fit in fits])

    designs, misfit = misfit_of(fits)
    # The goodness of fit is the layout's own, with one weight for all amplitudes: the
    # reweighted fit below explains its residuals by construction.
    chi2 = np.array([fit.rss for fit in fits]) / max(sigma2, 1e-300)
    led_error = float(misfit.model_errors[0]) if misfit.model_errors.size else 0.0
    reweighted = room.options.terminal_led_weights and _led_errors_seen(designs, led_error)
    # The room's own scatter, measured by its survey calibration on many degrees of freedom,
    # weights every terminal and, for terminals like the survey receiver (level, the layout
    # says, or residuals that the scatter explains), is its covariance's variance: one
    # request's few residuals would estimate it on next to nothing. A hand-held one's tilt
    # and gain are not in the survey's scatter, and under-covered with it: its radii come from
    # its own variances, where its residuals have the degrees of freedom to estimate them
    # (docs/decisions/measured-radii.md, docs/decisions/radii-in-rooms-of-five-leds.md).
    measured = room.fingerprint.layout.amplitude_error
    like_survey: list[TerminalFit] | None = None
    survey_positions: FloatArray | None = None
    # A Student-t scatter's fit is the t's likelihood: each amplitude weighted down as far
    # as its residual lies in the tails (iteratively reweighted least squares); its
    # covariance is then the t's, (nu + 3) / (nu + 1) the weighted fit's.
    tail_factor = 1.0
    if measured is not None:

        def scatter(fit: TerminalFit) -> FloatArray:
            return measured_variances(measured, room.scale, fit)

        like_survey = refitted(
            fits,
            scatter,
            search=room.options.weighted_pass_starts,
            likelihood=scatter,
            tail_dof=measured.tail_dof,
        )
        if measured.tail_dof is not None:
            for _ in range(_TAIL_REWEIGHTS):
                like_survey = refitted(
                    like_survey,
                    lambda fit: tail_weighted_variances(measured, room.scale, fit),
                    search=False,
                    likelihood=scatter,
                    tail_dof=measured.tail_dof,
                )
        if (
            not room.receivers_level
            and own_variances_estimable(like_survey, n_leds)
            and not scatter_explains(like_survey, n_leds, measured.tail_dof)
        ):
            # The fits keep the scatter's weights (its positions are the likelier), the
            # radii the request's own variances, as an uncalibrated room's.
            survey_positions = np.array([fit.position for fit in like_survey])
            like_survey = None
    if measured is not None and like_survey is not None:
        fits = like_survey
        designs, _ = misfit_of(fits, led_errors=False)
        misfit = measured_misfit(measured, designs, [fit.residual for fit in fits])
        reweighted = False
        if measured.tail_dof is not None:
            # The request's own model errors from t-reweighted residuals enter at their
            # estimates: F's widening for their few degrees of freedom assumes Gaussian
            # squares, and on a measured survey it widened the answers that erred least
            # (docs/decisions/measured-radii.md, "Heavy tails").
            misfit = replace(
                misfit, dofs=np.r_[misfit.dofs[0], np.full(misfit.dofs.size - 1, np.inf)]
            )
            tail_factor = (measured.tail_dof + 3.0) / (measured.tail_dof + 1.0)
    elif reweighted:
        # From the optimum only: weights estimated there are not the cost elsewhere (a
        # search under them went to worse places on beams far from their nominal shape).

        def with_led_errors(fit: TerminalFit) -> FloatArray:
            modelled = fit.jacobian[:, -1] / fit.data_weight
            return np.asarray(misfit.noise * sigma2 + led_error * modelled**2, dtype=np.float64)

        fits = refitted(fits, with_led_errors, search=False, likelihood=with_led_errors)
        # The LEDs' errors are in the weights now: a model error along them as well
        # would count them twice (radii too wide).
        designs, misfit = misfit_of(fits, led_errors=False)
    # What one request's residuals cannot estimate stays out of its covariance (a terminal
    # of a room with few LEDs: docs/decisions/few-residuals-few-model-errors.md).
    misfit = estimable_misfit(
        misfit, designs, [fit.residual for fit in fits], noise_estimated=like_survey is None
    )
    covariances = np.array(
        [
            tail_factor
            * predictive_covariances(design, misfit, np.array([[0, 1]]))[0]
            # A terminal whose own residual the pooled variances do not explain: its radius
            # says so (a terminal at a wrong optimum, or more impaired than the rest).
            * own_excess_widening(design, fit.residual, misfit)
            for design, fit in zip(designs, fits, strict=True)
        ]
    )
    if declared_tilt_sd > 0:
        for k, fit in enumerate(fits):
            if not (fit.free_tilt or own_normals[k] is not None):
                covariances[k] += terminal_tilt_covariance(room, fit, declared_tilt_sd)
    log_gains = np.array([fit.log_gain for fit in fits])
    # (a lone terminal's median is its own value: see check_amplitude_scale)
    typical_log_gain = log_gains[0] if n_terminals == 1 else np.median(log_gains)
    positions = np.array([fit.position for fit in fits])
    if survey_positions is not None:
        positions = survey_positions
    fit_quality = assess_fit(float(chi2.sum()), int(dof.sum()), math.exp(float(typical_log_gain)))
    if reweighted and fit_quality.quality != "scale_mismatch":
        seen = (
            f"the residuals grow with the amplitudes as if the LEDs were about "
            f"{100.0 * math.sqrt(led_error):.0f} % off their data sheet, and the brightest "
            "were weighted down for it (a survey calibration measures them)"
        )
        # The noise level was estimated from the same residuals: "to its noise" would
        # hide what they show.
        detail = seen if fit_quality.detail == FITS_TO_NOISE else f"{fit_quality.detail}; {seen}"
        fit_quality = replace(fit_quality, detail=detail)
    if measured is not None and like_survey is not None:
        # Each terminal's profile with the weights of its own fit, whose noise is 1: the
        # region the survey's scatter allows around the optimum it found. Its gain has the
        # fit's prior: the survey measured the receivers' gain, and a place that explains the
        # amplitudes only with a gain the fit would not take is not another optimum (with the
        # gain free, such places widened radii in rooms of five LEDs). A layout's nominal
        # scale can be off by more than that prior: there the gain stays free
        # (docs/decisions/radii-in-rooms-of-five-leds.md).
        far = np.vstack(
            [
                terminal_far_optima(
                    room,
                    values[k : k + 1],
                    positions[k : k + 1],
                    covariances[k : k + 1],
                    1.0,
                    led_weights=np.broadcast_to(fit.data_weight, (n_leds,)),
                    gain_sd=room.priors.log_gain_sd,
                )
                for k, fit in enumerate(fits)
            ]
        )
    else:
        far = terminal_far_optima(room, values, positions, covariances, sigma2)
    covariances, fit_quality = reported(room, positions, covariances, fit_quality, far)
    return Solution(
        positions=positions,
        grid_indices=room.fingerprint.layout.nearest_cell(positions),
        weights=np.ones(n_terminals),
        noise_power=n_terminals * sigma2 * room.scale**2,
        residual_norm=math.sqrt(sum(fit.rss for fit in fits)) * room.scale,
        n_iter=len(fits),
        converged=True,
        covariances=covariances,
        gains=np.exp(log_gains),
        heights=np.array([fit.height for fit in fits])
        if room.priors.fits_heights or heights is not None
        else None,
        fit=fit_quality,
    )


def profile_starts(
    room: PreparedRoom,
    values: FloatArray,
    variances: list[float | FloatArray],
    previous: FloatArray,
) -> list[FloatArray]:
    """Each terminal's grid cells where its weighted cost is lowest and lower than anywhere
    within ``_PROFILE_START_SPACING_M`` of its previous optimum: up to ``_PROFILE_STARTS``
    cells (S, 2) per terminal, that far from each other and from it.

    ``values`` (K, M) are the terminals' amplitudes, ``variances`` their K weights' variances
    (scalar or (M,)), ``previous`` (K, 2) their optima. The cost of cell n is
    ``sum_i w_i (a_i - g_n G_in)^2`` with ``w = 1 / variances`` and the gain ``g_n`` profiled
    out (its prior added where the room's priors give one): the weighted pass's own cost on
    the plane, which the first pass's starts (equal weights, any gain) do not rank by. Only
    a place the grid already shows to fit better than around the optimum is a start. Dense
    rooms only (large rooms start each terminal in its own window); none otherwise.
    """
    if not room.dense:
        return [np.empty((0, 2))] * len(values)
    weights = np.empty(values.shape)
    for k, variance in enumerate(variances):
        weights[k] = 1.0 / np.asarray(variance, dtype=np.float64)
    cells = dispatch(profile_cells_kernel, profile_cells_reference)(
        values,
        weights,
        room.gains,
        room.gains_sq,
        room.centres,
        np.asarray(previous, dtype=np.float64).reshape(-1, 2),
        room.priors.log_gain_sd,
    )
    return [room.centres[row[row >= 0]] for row in cells]


def profile_cells_kernel(
    values: FloatArray,
    weights: FloatArray,
    gains: FloatArray,
    gains_sq: FloatArray,
    centres: FloatArray,
    previous: FloatArray,
    log_gain_sd: float | None,
) -> IntArray:
    """:func:`profile_cells_reference` in one compiled call."""
    return np.asarray(
        compiled_starts.profile_cells_kernel(
            np.ascontiguousarray(values, dtype=np.float64),
            np.ascontiguousarray(weights, dtype=np.float64),
            np.ascontiguousarray(gains, dtype=np.float64),
            np.ascontiguousarray(gains_sq, dtype=np.float64),
            np.ascontiguousarray(centres, dtype=np.float64),
            np.ascontiguousarray(previous, dtype=np.float64),
            -1.0 if log_gain_sd is None else float(log_gain_sd),
            _PROFILE_START_SPACING_M,
            _PROFILE_STARTS,
        )
    )


def profile_cells_reference(
    values: FloatArray,
    weights: FloatArray,
    gains: FloatArray,
    gains_sq: FloatArray,
    centres: FloatArray,
    previous: FloatArray,
    log_gain_sd: float | None,
) -> IntArray:
    """The cells of :func:`profile_starts`, in NumPy: shape (K, ``_PROFILE_STARTS``), each
    terminal's in the order chosen, -1 after its last.

    ``values`` and ``weights`` (K, M) are the terminals' amplitudes and their weights,
    ``gains`` and ``gains_sq`` (M, N) the room's gains and their squares, ``centres`` (N, 2)
    the cells', ``previous`` (K, 2) the terminals' optima, ``log_gain_sd`` the gain's prior
    (None: none).
    """
    across = (weights * values) @ gains  # (K, N)
    energy = weights @ gains_sq  # (K, N)
    lit = energy > 0.0
    gain = np.where(lit, np.clip(across / np.where(lit, energy, 1.0), 1e-3, 1e3), 1.0)
    costs = np.sum(weights * values**2, axis=1)[:, None] - 2.0 * gain * across + gain**2 * energy
    if log_gain_sd is not None:
        costs += (np.log(gain) / log_gain_sd) ** 2
    xs, ys = centres[:, 0], centres[:, 1]
    cells = np.full((len(values), _PROFILE_STARTS), -1, dtype=np.int64)
    for k, (cost, point) in enumerate(zip(costs, previous, strict=True)):
        around = np.hypot(xs - point[0], ys - point[1]) < _PROFILE_START_SPACING_M
        # The cells still eligible, in grid order: most often none beats the optimum's
        # surroundings, and the search ends here.
        candidates = (
            np.flatnonzero(cost < cost[around].min()) if around.any() else np.arange(cost.size)
        )
        chosen = 0
        while candidates.size and chosen < _PROFILE_STARTS:
            index = candidates[np.argmin(cost[candidates])]
            if not np.isfinite(cost[index]):
                break
            cells[k, chosen] = index
            chosen += 1
            spread = np.hypot(xs[candidates] - xs[index], ys[candidates] - ys[index])
            candidates = candidates[spread >= _PROFILE_START_SPACING_M]
    return cells


def terminal_tilt_covariance(room: PreparedRoom, fit: TerminalFit, tilt_sd: float) -> FloatArray:
    """A terminal's position covariance from a photodiode tilt of the layout's spread
    that its fit holds level, shape (2, 2): as :func:`.uncertainty.tilt_covariances`, with the
    terminal's own whitened Jacobian (position first)."""
    gradient = shape_gradients(room, fit.position[np.newaxis, :], np.array([fit.height]))[0]
    weight = np.reshape(fit.data_weight, (-1, 1))
    columns = weight * math.exp(fit.log_gain) * gradient[:, 1:3]  # (M, 2)
    position = np.array([[0, 1]])
    covariances = response_covariances(fit.normal, fit.jacobian.T, columns, position, tilt_sd)
    return np.asarray(covariances[0])


def terminal_misfit_columns(
    room: PreparedRoom,
    fit: TerminalFit,
    height_known: bool,
    normal_known: bool,
    led_errors: bool = True,
) -> list[FloatArray]:
    """Whitened derivatives of a terminal's amplitudes along the errors its fit does not
    fit, as :func:`.uncertainty.misfit_columns`: each LED's relative error, (M, M), then the
    photodiode's tilt, (M, 2), and its height, (M, 1), unless fitted or sent by the
    terminal (or, for the tilt, the layout's photodiodes are level), or for the LEDs'
    errors ``led_errors`` False (their variance already in the fit's weights) (then
    (M, 0): every terminal keeps the same components)."""
    whitened = fit.jacobian[:, -1]  # the log gain's column: the whitened amplitudes
    # LEDs out of view give zero columns: left out (a large room has hundreds).
    seen = (whitened != 0.0) & led_errors
    columns = [np.diag(whitened)[:, seen]]
    gradient = shape_gradients(room, fit.position[np.newaxis, :], np.array([fit.height]))[0]
    scale = np.reshape(fit.data_weight, (-1, 1)) * math.exp(fit.log_gain)
    unknown_tilt = not (fit.free_tilt or normal_known or room.receivers_level)
    unknown_height = not (fit.free_height or height_known)
    columns.append(scale * gradient[:, 1:3] if unknown_tilt else gradient[:, :0])
    columns.append(scale * gradient[:, 0:1] if unknown_height else gradient[:, :0])
    return columns


def _led_errors_seen(designs: list[MisfitDesign], led_error: float) -> bool:
    """Whether the LEDs' relative errors, variance ``led_error`` (the first model error of
    each design, one per terminal), explain more of the residuals' sum of squares than the
    noise's chi-square scatters (``_LED_WEIGHT_SIGNIFICANCE`` standard deviations): where the
    room's LEDs are as modelled, a moment estimate of ``led_error`` above 0 is the noise's
    chance; and, pooled over several terminals, whether it is an LED's error at all (relative
    sd at most ``_MAX_LED_ERROR_SD``)."""
    if not led_error > 0.0 or (len(designs) > 1 and led_error > _MAX_LED_ERROR_SD**2):
        return False
    seen = led_error * sum(float(design.error_leverages[:, 0].sum()) for design in designs)
    noise_dof = sum(float(design.noise_leverage.sum()) for design in designs)
    return seen > _LED_WEIGHT_SIGNIFICANCE * math.sqrt(2.0 * noise_dof)
