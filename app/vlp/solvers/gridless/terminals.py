"""Per-terminal fits: each terminal's own amplitudes locate that terminal.

When terminals send their amplitudes ``a_k`` (M numbers each) rather than only their sums,
every terminal is a single-target problem with M equations:

.. math::

    a_k = e^{u_k} g(p_k, z_k, n_k) + \\epsilon_k, \\qquad \\epsilon_k \\sim N(0, \\sigma^2 I),

with ``g`` the normalised channel (line of sight for the photodiode's normal ``n_k``, plus
the diffuse reflections of the room), ``u_k`` the terminal's log amplitude gain (Gaussian
prior) and ``z_k`` its height (known, or free with the room's prior). This is strictly more
information than any aggregate of the same amplitudes, and labels come for free. Private:
callers validate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from ..._kernels import dispatch
from ...typing import FloatArray
from .._data_support import detected_leds, leaves_dof, supports_nuisance
from ._compiled import terminal as compiled_terminal
from ._compiled.channel import channel_constants
from .channel import ChannelKernel
from .channel_rows import channel_rows
from .lm import (
    PROJECTED_MAX_REJECTIONS,
    TERMINAL_COST_TOL,
    TERMINAL_INITIAL_DAMPING,
    TERMINAL_STEP_TOL_M,
    LMSettings,
    least_squares_normal_equations,
    least_squares_point,
    levenberg_marquardt,
    whitening_weight,
)
from .state import (
    MAX_LOG_GAIN,
    Priors,
)

__all__ = ["TerminalFit", "fit_terminal", "los_with_normal", "starting_cells", "terminal_model"]

# Candidate starts per terminal (the best grid points of its own correlation, kept apart).
_STARTS = 3
# Each start's LM: stopped when its position moves by less than TERMINAL_STEP_TOL_M or an
# accepted step lowers the cost by less than TERMINAL_COST_TOL of it.
_LM = LMSettings(
    max_iter=30,
    damping=TERMINAL_INITIAL_DAMPING,
    max_rejections=PROJECTED_MAX_REJECTIONS,
    cost_tol=TERMINAL_COST_TOL,
    step_tol=TERMINAL_STEP_TOL_M,
    n_positions=2,
    before_trial=False,
)
# A fitted tilt (tangent of its components) stays within +-45 degrees.
_MAX_TILT = 1.0
# Cost decrease a fitted tilt must bring to be kept: 2 + 3 sqrt(2 * 2).
_TILT_SIGNIFICANCE = 8.0
# ... and a free gain, over the gain held at 1: 2 per parameter (Akaike). Every phone's
# gain differs a little, so the test leans to freeing it: at 3 standard deviations (5.2)
# the gains held at 1 biased a 10 % gain spread (docs/decisions/terminal-gain-gate.md).
_GAIN_SIGNIFICANCE = 2.0
# Prior sd of a log gain held at 0: its information dwarfs the data's, so the normal matrix
# (and the covariance from it) is that of a fit without the gain, in the same layout.
_HELD_LOG_GAIN_SD = 1e-6


@dataclass(frozen=True)
class TerminalFit:
    """One terminal's fit: position (2,) m, height m, log gain, residual sum of squares,
    the normal matrix of the whitened fit (for its covariance) and the parameter count;
    the whitened data Jacobian (M, P) and data residual (M,) at the optimum (the log gain's
    column, last, is the whitened fitted amplitudes), the data's whitening weight and
    whether the height and the tilt were fitted."""

    position: FloatArray
    height: float
    log_gain: float
    rss: float
    normal: FloatArray
    n_params: int
    cost: float = 0.0
    jacobian: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    residual: FloatArray = field(default_factory=lambda: np.zeros(0))
    data_weight: float | FloatArray = 1.0
    free_height: bool = False
    free_tilt: bool = False


def los_with_normal(
    kernel: ChannelKernel, point: FloatArray, normal: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Normalised line-of-sight gains (M,) and their gradient (M, 3) w.r.t. the receiver's
    ``(x, y, z)`` for a photodiode of unit ``normal`` at ``point = (x, y, z)``.

    ``h = pref D^m (n . v) / d^(m+3)`` with ``v`` = LED minus receiver, ``D = v_z``;
    ``grad h = h (-m / D e_z - n / (n . v) + (m + 3) v / d^2)``; 0 outside the FOV.
    """
    offsets = kernel.led_xyz - point  # (M, 3): LED minus receiver
    drop = np.maximum(offsets[:, 2], 1e-9)
    dist2 = np.einsum("ij,ij->i", offsets, offsets)
    facing = offsets @ normal
    in_view = (facing > 0.0) & (facing * facing >= kernel.cos_fov2 * dist2)
    orders = kernel.orders
    gains = np.where(
        in_view,
        kernel.free_height_factor
        * drop**orders
        * np.maximum(facing, 1e-300)
        * dist2 ** (-(orders + 3.0) / 2.0),
        0.0,
    )
    safe_facing = np.where(in_view, facing, 1.0)
    gradient = gains[:, None] * (
        -(orders / drop)[:, None] * np.array([0.0, 0.0, 1.0])
        - normal[None, :] / safe_facing[:, None]
        + ((orders + 3.0) / dist2)[:, None] * offsets
    )
    if kernel.has_tilt:
        # A tilted LED: times (c / D)^m, c = n_led . (r - s) (ChannelKernel's module notes).
        emitting = -np.einsum("ij,ij->i", offsets, kernel.normals)
        ahead = emitting > 0
        safe = np.where(ahead, emitting, 1.0)
        factor = np.where(ahead, (safe / drop) ** orders, 0.0)
        gains = gains * factor
        extra = orders[:, None] * (
            kernel.normals / safe[:, None] + np.array([0.0, 0.0, 1.0]) / drop[:, None]
        )
        gradient = gradient * factor[:, None] + gains[:, None] * extra
    if kernel.has_beams:
        beam, along = kernel.beam_towards(-offsets[:, None, :])
        gradient = gradient * beam + gains[:, None] * along[:, 0, :]
        gains = gains * beam[:, 0]
    return gains, gradient


def starting_cells(scores: FloatArray, centres: FloatArray, min_distance_m: float) -> list[int]:
    """Up to ``_STARTS`` best grid cells by ``scores``, each ``min_distance_m`` from the others."""
    candidates = np.argsort(scores)[::-1][: 50 * _STARTS]
    xs, ys = centres[candidates, 0], centres[candidates, 1]
    # Each chosen cell closes the candidates within reach of it at once (one vector
    # operation, not one distance per candidate and chosen cell).
    open_ = np.ones(candidates.size, dtype=bool)
    chosen: list[int] = []
    while len(chosen) < _STARTS:
        free = np.flatnonzero(open_)
        if free.size == 0:
            break
        at = int(free[0])
        chosen.append(int(candidates[at]))
        open_[at] = False
        open_ &= np.hypot(xs - xs[at], ys - ys[at]) >= min_distance_m
    return chosen


def fit_terminal(
    kernel: ChannelKernel,
    amplitudes: FloatArray,
    starts: FloatArray,
    *,
    priors: Priors,
    sigma2: float | FloatArray | None,
    height: float | None,
    normal: FloatArray | None,
    tilt_sd: float | None = None,
    tilt_spread_known: bool = False,
) -> TerminalFit:
    """Fit one terminal from each start, keep the lowest cost.

    With priors (``sigma2`` given), the gain is held at 1 and an unknown photodiode kept
    level unless freeing them lowers the cost by more than chance would; an unknown tilt
    whose spread the room declares is always fitted with that prior.

    Parameters
    ----------
    kernel : ChannelKernel
    amplitudes : ndarray of shape (M,)
        The terminal's amplitudes in normalised units.
    starts : ndarray of shape (S, 2)
        Starting positions, metres.
    priors : Priors
        ``log_gain_sd`` (None: the gain free without a prior) and the heights' prior.
    sigma2 : float or None
        Noise variance (normalised units) weighting the data against the priors; None fits
        without priors (a first pass that estimates the noise).
    height : float or None
        The terminal's own height when it sent it.
    normal : ndarray of shape (3,) or None
        Its photodiode's unit normal when it sent it (None: unknown).
    tilt_sd : float or None
        Prior standard deviation of each component of an unknown photodiode's tilt
        (tangent units; with priors only); None keeps an unknown normal straight up.
    tilt_spread_known : bool
        ``tilt_sd`` is the room's own tilt spread (the layout's ``receiver_tilt_sd``), not a
        default guess: the tilt is then always fitted with it as the prior (a maximum a
        posteriori estimate), never held level by the significance test.
    """
    best: TerminalFit | None = None
    held_gain_sd: float | None = None  # the gain's prior sd when it is held at 1
    weight = whitening_weight(amplitudes, sigma2) if sigma2 is not None else 1.0
    free_height = height is None and priors.fits_heights
    z0 = priors.height_mean if height is None else float(height)
    for start in starts:
        fit = _fit_from(
            kernel,
            amplitudes,
            start,
            z0,
            free_height,
            priors,
            weight if sigma2 is not None else None,
            normal,
            None,
        )
        if best is None or fit.rss < best.rss:
            best = fit
    assert best is not None
    # [data-support hook] how many LEDs this terminal's data really has (see _data_support).
    n_seen = detected_leds(amplitudes, sigma2)
    if sigma2 is not None and priors.log_gain_sd is not None:
        # The gain is kept free only when the data ask for it, as the tilt below: free, it
        # trades against the distance to the brightest LEDs and costs a terminal exactly as
        # modelled accuracy (docs/decisions/terminal-gain-gate.md).
        held_priors = replace(priors, log_gain_sd=_HELD_LOG_GAIN_SD)
        held = _fit_from(
            kernel, amplitudes, best.position, z0, free_height, held_priors, weight, normal, None
        )
        # [data-support hook] a free gain also needs the detected LEDs to leave room for it.
        gain_supported = leaves_dof(n_seen, best.n_params - 1, 1)
        if held.cost - best.cost <= _GAIN_SIGNIFICANCE or not gain_supported:
            best, priors, held_gain_sd = held, held_priors, priors.log_gain_sd
    # [data-support hook] no tilt where the detected LEDs leave no degrees of freedom for it.
    if normal is not None or tilt_sd is None or not leaves_dof(n_seen, best.n_params, 2):
        return _with_gain_prior(best, held_gain_sd)
    if sigma2 is None:
        # The noise estimate comes from a fit that may tilt (no prior): a tilted room's
        # residuals would otherwise count its tilts as noise.
        return _fit_from(
            kernel, amplitudes, best.position, z0, free_height, priors, None, None, tilt_sd
        )
    # An unknown tilt is fitted too, and kept only when it lowers the cost by more than its
    # two components would by chance (mean plus three standard deviations of a chi-square
    # with 2 degrees of freedom): tilt and position trade off, so a free tilt costs a level
    # terminal accuracy (measured in docs/decisions/declared-tilt-spread.md). A tilt spread the
    # room declares
    # is kept always: a tilt is nearly a shift, its cost decrease mostly too small for the
    # test, and the prior is then the room's own (docs/decisions/declared-tilt-spread.md).
    tilted = _fit_from(
        kernel, amplitudes, best.position, z0, free_height, priors, weight, None, tilt_sd
    )
    # [data-support hook] the count rule and a BIC-type price next to the chance level.
    significant = supports_nuisance(
        best.cost - tilted.cost, n_seen, best.n_params, 2, _TILT_SIGNIFICANCE
    )
    chosen = tilted if tilt_spread_known or significant else best
    return _with_gain_prior(chosen, held_gain_sd)


def _with_gain_prior(fit: TerminalFit, gain_sd: float | None) -> TerminalFit:
    """``fit`` (its gain held at 1) with the information of the gain's own prior ``gain_sd``
    in its normal matrix instead of the holding one, so that its covariance still carries
    what a gain error too small for the test would do to the position (held, the radii
    were too narrow in a realistic room: docs/decisions/terminal-gain-gate.md); unchanged when
    None."""
    if gain_sd is None:
        return fit
    normal = fit.normal.copy()
    normal[-1, -1] += 1.0 / gain_sd**2 - 1.0 / _HELD_LOG_GAIN_SD**2
    return replace(fit, normal=normal)


def _tilted_normal(tilt: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit normal ``(tx, ty, 1) / |.|`` of a tilt ``(tx, ty)`` and its derivative (3, 2)."""
    raw = np.array([tilt[0], tilt[1], 1.0])
    length = float(np.linalg.norm(raw))
    normal = raw / length
    derivative = (np.eye(3)[:, :2] - np.outer(normal, normal[:2])) / length
    return normal, derivative


def terminal_model(
    kernel: ChannelKernel,
    theta: FloatArray,
    free_height: bool,
    z0: float,
    normal: FloatArray | None,
    free_tilt: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Gains ``g`` (M,) and their gradient (M, 3 or 5) at ``theta = [x, y, (z), (tx, ty), u]``:
    columns x, y, z, then the tilt's two components when the tilt is free."""
    x, y = float(theta[0]), float(theta[1])
    z = float(theta[2]) if free_height else z0
    if normal is None and not free_tilt:
        rows = channel_rows(kernel, np.array([x]), np.array([y]), np.array([z]), False)
        return np.asarray(rows[0, 0]), np.asarray(rows[1:, 0].T)
    at = 3 if free_height else 2
    tilt_derivative = None
    if free_tilt:
        normal, tilt_derivative = _tilted_normal(theta[at : at + 2])
    assert normal is not None
    point = np.array([x, y, z])
    los, gradient = los_with_normal(kernel, point, normal)
    if tilt_derivative is not None:
        offsets = kernel.led_xyz - point
        facing = offsets @ normal
        along_normal = np.where(los > 0.0, los / np.where(los > 0.0, facing, 1.0), 0.0)
        tilt_gradient = (along_normal[:, None] * offsets) @ tilt_derivative
        gradient = np.column_stack((gradient, tilt_gradient))
    if kernel.diffuse is not None:
        values, along_x, along_y, along_z = kernel.diffuse.evaluate(
            np.array([x]), np.array([y]), np.array([z])
        )
        scale = kernel.pilot_over_scale
        los = los + values[:, 0] * scale
        gradient[:, :3] += (
            np.column_stack((along_x[:, 0], along_y[:, 0], along_z[:, 0])) * (scale[:, None])
        )
    return los, gradient


def _fit_from(
    kernel: ChannelKernel,
    amplitudes: FloatArray,
    start: FloatArray,
    z0: float,
    free_height: bool,
    priors: Priors,
    weight: float | FloatArray | None,
    normal: FloatArray | None,
    tilt_sd: float | None,
) -> TerminalFit:
    """Projected LM on ``[x, y, (z), (tx, ty), u]`` with the Gaussian priors as
    pseudo-residuals (the tilt is free when ``tilt_sd`` is given and no normal was sent).

    With the compiled kernels the whole fit is one call (:func:`terminal_fit_kernel`; its
    NumPy reference :func:`terminal_fit_reference`)."""
    problem, theta, lower, upper = terminal_fit_arguments(
        kernel, amplitudes, start, z0, free_height, priors, weight, normal, tilt_sd
    )
    theta, residual, jacobian, cost = dispatch(terminal_fit_kernel, terminal_fit_reference)(
        problem, theta, lower, upper
    )
    return _terminal_fit(
        theta,
        residual,
        jacobian,
        cost,
        amplitudes.shape[0],
        problem.data_weight,
        z0,
        free_height,
        problem.free_tilt,
    )


def terminal_fit_arguments(
    kernel: ChannelKernel,
    amplitudes: FloatArray,
    start: FloatArray,
    z0: float,
    free_height: bool,
    priors: Priors,
    weight: float | FloatArray | None,
    normal: FloatArray | None,
    tilt_sd: float | None,
) -> tuple[TerminalProblem, FloatArray, FloatArray, FloatArray]:
    """:func:`_fit_from`'s arguments as :func:`terminal_fit_reference` takes them: the
    problem, the start's theta and the bounds."""
    with_priors = weight is not None
    free_tilt = normal is None and tilt_sd is not None
    # The log gain starts at the start's least-squares gain (set by the fit).
    theta = np.array(
        [
            start[0],
            start[1],
            *([z0] if free_height else []),
            *([0.0, 0.0] if free_tilt else []),
            0.0,
        ]
    )
    lower, upper = _bounds(
        kernel, priors, free_height, free_tilt, with_priors and priors.log_gain_sd is not None
    )
    data_weight = weight if weight is not None else 1.0
    problem = TerminalProblem(
        kernel,
        amplitudes,
        z0,
        free_height,
        free_tilt,
        normal,
        priors,
        with_priors,
        data_weight,
        tilt_sd,
    )
    return problem, theta, lower, upper


# The kernel's normal argument when the terminal sent none (it reads it only when one was).
_NO_NORMAL = np.zeros(3)


def _bounds(
    kernel: ChannelKernel, priors: Priors, free_height: bool, free_tilt: bool, gain_prior: bool
) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds of ``[x, y, (z), (tx, ty), u]``: the room, the heights' prior
    bounds, +-45 degrees of tilt, and a log gain within +-20 (within its prior's reach when
    it has one). Kept on the kernel per layout of theta (many fits ask for the same):
    callers must not write into them."""
    key = (free_height, free_tilt, gain_prior, priors.height_bounds if free_height else None)
    kept: dict[object, tuple[FloatArray, FloatArray]] = kernel.__dict__.setdefault(
        "_terminal_bounds", {}
    )
    found = kept.get(key)
    if found is not None:
        return found
    lower = np.array(
        [
            0.0,
            0.0,
            *([priors.height_bounds[0]] if free_height else []),
            *([-_MAX_TILT, -_MAX_TILT] if free_tilt else []),
            -20.0,
        ]
    )
    upper = np.array(
        [
            *kernel.bounds,
            *([priors.height_bounds[1]] if free_height else []),
            *([_MAX_TILT, _MAX_TILT] if free_tilt else []),
            20.0,
        ]
    )
    if gain_prior:
        lower[-1], upper[-1] = -MAX_LOG_GAIN - 3.0, MAX_LOG_GAIN + 3.0
    kept[key] = (lower, upper)
    return lower, upper


class TerminalProblem(NamedTuple):
    """What one terminal's fit is given, but its start and bounds: its amplitudes, the
    receivers' height ``z0``, which of height and tilt are free, the photodiode normal it
    sent (None: none), the priors (pseudo-residuals only ``with_priors``), the data's
    weight (a scalar or per value) and the tilt's standard deviation."""

    kernel: ChannelKernel
    amplitudes: FloatArray
    z0: float
    free_height: bool
    free_tilt: bool
    normal: FloatArray | None
    priors: Priors
    with_priors: bool
    data_weight: float | FloatArray
    tilt_sd: float | None


def terminal_fit_kernel(
    problem: TerminalProblem, theta: FloatArray, lower: FloatArray, upper: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """:func:`terminal_fit_reference` in one compiled call (in NumPy for a channel without a
    compiled form)."""
    constants = channel_constants(problem.kernel)
    if constants is None:
        return terminal_fit_reference(problem, theta, lower, upper)
    amplitudes, data_weight, normal, priors = (
        problem.amplitudes,
        problem.data_weight,
        problem.normal,
        problem.priors,
    )
    fitted, residual, jacobian, cost = compiled_terminal.terminal_fit_kernel(
        *constants,
        np.ascontiguousarray(amplitudes, dtype=np.float64),
        # fresh writable arrays: one compiled signature for all (warm_up compiles it)
        np.array(data_weight, dtype=np.float64)
        if isinstance(data_weight, np.ndarray)
        else np.full(amplitudes.shape[0], float(data_weight)),
        theta,
        lower,
        upper,
        (
            bool(problem.free_height),
            normal is not None,
            bool(problem.free_tilt),
            float(problem.z0),
        ),
        _NO_NORMAL if normal is None else np.array(normal, dtype=np.float64),
        (
            bool(problem.with_priors),
            -1.0 if priors.log_gain_sd is None else float(priors.log_gain_sd),
            float(priors.height_mean),
            float(priors.height_sd),
            -1.0 if problem.tilt_sd is None else float(problem.tilt_sd),
        ),
        tuple(_LM),
    )
    return fitted, residual, jacobian, cost


def terminal_fit_reference(
    problem: TerminalProblem, theta: FloatArray, lower: FloatArray, upper: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Projected LM from ``theta`` (its log gain replaced by the least-squares gain of the
    start's gains, within :data:`~._compiled.terminal.START_LOG_GAIN_PRIOR_SDS` prior sds of
    a gain prior's mean) within ``[lower, upper]``, in NumPy: theta, whitened residual,
    Jacobian and cost at LM's last accepted point."""
    kernel, amplitudes, z0 = problem.kernel, problem.amplitudes, problem.z0
    free_height, free_tilt, normal = problem.free_height, problem.free_tilt, problem.normal
    priors = problem.priors if problem.with_priors else None
    data_weight, tilt_sd = problem.data_weight, problem.tilt_sd
    theta = theta.copy()
    start = theta[:2]
    axes = (3 if free_height else 2) + (2 if free_tilt else 0)
    gradient_columns = [0, 1, *([2] if free_height else []), *([3, 4] if free_tilt else [])]
    gains0, _ = terminal_model(kernel, np.array([start[0], start[1], z0]), free_height, z0, normal)
    norm = float(gains0 @ gains0)
    theta[-1] = math.log(max(float(gains0 @ amplitudes) / norm, 1e-6)) if norm > 0 else 0.0
    if priors is not None and priors.log_gain_sd is not None:
        reach = compiled_terminal.START_LOG_GAIN_PRIOR_SDS * priors.log_gain_sd
        theta[-1] = min(max(float(theta[-1]), -reach), reach)
    # Per-value weights multiply the Jacobian's rows.
    row_weight = data_weight[:, None] if isinstance(data_weight, np.ndarray) else data_weight
    tilt_at = 3 if free_height else 2

    def evaluate(params: FloatArray) -> tuple[float, tuple[FloatArray, FloatArray]]:
        gains, gradient = terminal_model(kernel, params, free_height, z0, normal, free_tilt)
        amp = math.exp(float(params[-1]))
        residual = data_weight * (amplitudes - amp * gains)
        jacobian = np.empty((amplitudes.shape[0], params.shape[0]))
        jacobian[:, :axes] = row_weight * amp * gradient[:, gradient_columns]
        jacobian[:, -1] = data_weight * amp * gains
        rows_r: list[float] = []
        rows_j: list[FloatArray] = []
        if priors is not None and priors.log_gain_sd is not None:
            rows_r.append(-float(params[-1]) / priors.log_gain_sd)
            row = np.zeros(params.shape[0])
            row[-1] = 1.0 / priors.log_gain_sd
            rows_j.append(row)
        if priors is not None and free_height:
            rows_r.append(-(float(params[2]) - priors.height_mean) / priors.height_sd)
            row = np.zeros(params.shape[0])
            row[2] = 1.0 / priors.height_sd
            rows_j.append(row)
        if priors is not None and free_tilt and tilt_sd is not None:
            for offset in (0, 1):
                rows_r.append(-float(params[tilt_at + offset]) / tilt_sd)
                row = np.zeros(params.shape[0])
                row[tilt_at + offset] = 1.0 / tilt_sd
                rows_j.append(row)
        if rows_r:
            residual = np.concatenate((residual, rows_r))
            jacobian = np.vstack((jacobian, np.array(rows_j)))
        return least_squares_point(residual, jacobian)

    theta, cost, _, (residual, jacobian) = levenberg_marquardt(
        evaluate, least_squares_normal_equations, theta, lower, upper, _LM
    )
    return theta, residual, jacobian, cost


def _terminal_fit(
    theta: FloatArray,
    residual: FloatArray,
    jacobian: FloatArray,
    cost: float,
    n_data: int,
    data_weight: float | FloatArray,
    z0: float,
    free_height: bool,
    free_tilt: bool,
) -> TerminalFit:
    """The fit at LM's last accepted point (whitened residual and Jacobian, data rows
    first)."""
    data_residual = residual[:n_data] / data_weight
    return TerminalFit(
        position=theta[:2].copy(),
        height=float(theta[2]) if free_height else z0,
        log_gain=float(theta[-1]),
        rss=float(data_residual @ data_residual),
        cost=float(cost),
        normal=jacobian.T @ jacobian,
        n_params=theta.shape[0],
        jacobian=jacobian[:n_data].copy(),
        residual=residual[:n_data].copy(),
        data_weight=data_weight,
        free_height=free_height,
        free_tilt=free_tilt,
    )
