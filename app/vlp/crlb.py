"""Cramér-Rao lower bounds on the position error (the physical floor of any solver).

Three bounds:

- :func:`single_target_crlb`: one terminal, its own amplitudes ``a_i = g_i(p) + n_i``
  (``g_i = h_i x_i``, ``n_i ~ N(0, sigma^2)`` i.i.d.).
- :func:`aggregated_crlb`: K terminals seen only through the aggregated measurement
  (``vech(R)`` or ``p``), all 2K coordinates jointly, with the Gaussian approximation of the
  aggregated noise (exact first and second moments).
- :func:`nuisance_crlb`: either form (or every terminal's own amplitudes) with nuisance
  parameters (gains, common scale, heights, tilts, LED tolerances) under Gaussian priors,
  in rooms with reflections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .channel import channel_gain_gradients, lambertian_order, los_gain_gradients
from .errors import GeometryError, MeasurementError
from .layout import Layout
from .measurements import Model
from .reflections import diffuse_gains
from .typing import FloatArray

__all__ = [
    "AggregatedBound",
    "Nuisances",
    "aggregated_correlation_covariance",
    "aggregated_crlb",
    "nuisance_crlb",
    "single_target_crlb",
]


def _check_noise(noise_std: float) -> None:
    if not (np.isfinite(noise_std) and noise_std > 0):
        raise MeasurementError(
            f"noise_std must be positive and finite, got {noise_std!r}", field="noise_std"
        )


def _check_positions(layout: Layout, positions: FloatArray) -> FloatArray:
    pts = np.asarray(positions, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 1:
        raise GeometryError(
            f"positions must have shape (K, 2) with K >= 1, got {pts.shape}", field="positions"
        )
    inside = (
        (pts >= 0).all()
        and (pts[:, 0] <= layout.room.length).all()
        and (pts[:, 1] <= layout.room.width).all()
    )
    if not (np.isfinite(pts).all() and inside):
        raise GeometryError("positions must be finite and inside the room", field="positions")
    return pts


def single_target_crlb(layout: Layout, position: FloatArray, noise_std: float) -> float:
    """RMS position bound (metres) of one terminal from its own M pilot amplitudes.

    Parameters
    ----------
    layout : Layout
    position : ndarray of shape (2,)
        True ``(x, y)``, metres, at the receivers' height.
    noise_std : float
        sigma, standard deviation of one amplitude's noise (amplitude units, i.e. those of
        ``h x``; see :func:`app.vlp.simulation.noise_std_for_snr`).

    Returns
    -------
    bound : float
        ``sqrt(trace(F^-1))``, metres; ``inf`` when fewer than two LEDs are in view.

    Raises
    ------
    GeometryError, MeasurementError

    Notes
    -----
    With ``a_i = g_i(p) + n_i`` the Fisher information of ``p`` is
    ``F = sum_i grad g_i grad g_i^T / sigma^2``. For an LED ``i`` at horizontal position
    ``s_i``, height ``dz_i`` above the receivers and Lambertian order ``m_i``,
    ``g_i = C_i dz_i^(m_i+1) / d_i^(m_i+3)`` with ``d_i^2 = |p - s_i|^2 + dz_i^2``, so
    ``grad g_i = -(m_i + 3) g_i (p - s_i) / d_i^2`` and

    .. math::

        F = \\sum_i (m_i + 3)^2\\, \\mathrm{SNR}_i\\, \\frac{(p - s_i)(p - s_i)^T}{d_i^4},
        \\qquad \\mathrm{SNR}_i = g_i(p)^2 / \\sigma^2,

    the aggregated Fisher information docs/results/accuracy.md evaluates, where ``SNR_i`` is the
    link SNR at ``p``. In our SNR convention
    (``SNR = mean_ij g_ij^2 / sigma^2`` over LEDs and grid points)
    ``SNR_i = SNR * g_i(p)^2 / mean(J)``. LEDs outside the FOV contribute nothing.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> bound = single_target_crlb(paper_layout(), np.array([2.0, 2.0]), 1e-6)
    >>> bound > 0
    True
    """
    _check_noise(noise_std)
    pts = _check_positions(layout, np.asarray(position, dtype=np.float64).reshape(1, 2))
    _, grads = channel_gain_gradients(layout, pts)
    grads = grads[:, 0, :] * layout.pilot_amplitudes[:, None]  # (M, 2)
    fisher = grads.T @ grads / noise_std**2
    return _rms_bound(fisher)


def _rms_bound(fisher: FloatArray) -> float:
    try:
        inverse = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return float("inf")
    trace = float(np.trace(inverse))
    if not np.isfinite(trace) or trace <= 0 or np.linalg.cond(fisher) > 1e14:
        return float("inf")
    return float(np.sqrt(trace))


@dataclass(frozen=True)
class AggregatedBound:
    """The aggregated-model bound.

    Attributes
    ----------
    per_target : ndarray of shape (K,)
        ``sqrt(var_x + var_y)`` bound of each target, metres.
    mean : float
        Mean of ``per_target``, metres.
    covariance : ndarray of shape (2K, 2K)
        The inverse Fisher block of the coordinates ``(x_1, y_1, x_2, ...)``, m^2.
    """

    per_target: FloatArray
    mean: float
    covariance: FloatArray


def aggregated_correlation_covariance(
    signal: FloatArray, noise_var: float, n_targets: int
) -> FloatArray:
    """Covariance of ``vech(R)`` for ``R = sum_k (g_k + n_k)(g_k + n_k)^T``.

    Parameters
    ----------
    signal : ndarray of shape (M, M)
        ``S = sum_k g_k g_k^T``, squared amplitude units.
    noise_var : float
        sigma^2 of one amplitude.
    n_targets : int
        K.

    Returns
    -------
    covariance : ndarray of shape (M(M+1)/2, M(M+1)/2)

    Notes
    -----
    The cross terms ``g n^T + n g^T`` give ``sigma^2 (S_ij d_lm + S_lm d_ij + S_im d_lj +
    S_lj d_im)`` and the Wishart term ``sum_k n_k n_k^T`` gives
    ``K sigma^4 (d_ij d_lm + d_im d_lj)`` (Isserlis), uncorrelated with the cross terms
    (odd moments vanish). Both combine to the first form with ``S`` replaced by
    ``M0 = S + K sigma^2 / 2 I``.
    """
    n_leds = signal.shape[0]
    m0 = signal + 0.5 * n_targets * noise_var * np.eye(n_leds)
    row, col = np.triu_indices(n_leds)  # entry (i, l) of R
    eye = np.eye(n_leds)
    cov = (
        m0[row[:, None], row[None, :]] * eye[col[:, None], col[None, :]]
        + m0[col[:, None], col[None, :]] * eye[row[:, None], row[None, :]]
        + m0[row[:, None], col[None, :]] * eye[col[:, None], row[None, :]]
        + m0[col[:, None], row[None, :]] * eye[row[:, None], col[None, :]]
    )
    return np.asarray(noise_var * cov)


def aggregated_crlb(
    layout: Layout,
    positions: FloatArray,
    noise_std: float,
    model: Model = "correlation",
    *,
    noise_power_known: bool = False,
) -> AggregatedBound:
    """Bound of all 2K coordinates jointly from one aggregated measurement.

    Parameters
    ----------
    layout : Layout
    positions : ndarray of shape (K, 2)
        True positions, metres.
    noise_std : float
        sigma of one amplitude's noise (amplitude units).
    model : {"correlation", "power"}, default="correlation"
    noise_power_known : bool, default=False
        When False the noise atom's coefficient ``K sigma^2`` is a nuisance parameter
        estimated jointly (as the solvers do); the bound is then slightly larger.

    Returns
    -------
    AggregatedBound

    Notes
    -----
    Mean ``mu = sum_k phi(g_k) + K sigma^2 a`` with ``phi(g) = vech(g g^T)`` (``g o g``
    for power) and ``a`` the noise atom; Fisher ``F = J^T C^-1 J`` with ``J`` the Jacobian
    of ``mu`` with respect to ``(x_1, y_1, ..., x_K, y_K[, s])`` and ``C`` the covariance of
    :func:`aggregated_correlation_covariance` (its diagonal for power:
    ``4 sigma^2 S_ii + 2 K sigma^4``). The Gaussian approximation keeps the exact first two
    moments but ignores the mean's dependence of ``C`` on the positions.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> b = aggregated_crlb(paper_layout(), np.array([[1.0, 1.0], [3.0, 2.5]]), 1e-6)
    >>> b.per_target.shape
    (2,)
    """
    _check_noise(noise_std)
    pts = _check_positions(layout, positions)
    if model not in ("power", "correlation"):
        raise MeasurementError(
            f"model must be 'power' or 'correlation', got {model!r}", field="model"
        )
    n_targets = pts.shape[0]
    gains, grads = channel_gain_gradients(layout, pts)
    pilots = layout.pilot_amplitudes[:, None]
    gains = gains * pilots  # (M, K)
    grads = grads * pilots[:, :, None]  # (M, K, 2)
    var = noise_std**2
    n_leds = layout.n_leds
    columns: list[FloatArray] = []
    if model == "correlation":
        row, col = np.triu_indices(n_leds)
        for k in range(n_targets):
            for axis in range(2):
                d = grads[:, k, axis]
                columns.append(gains[row, k] * d[col] + d[row] * gains[col, k])
        atom = (row == col).astype(np.float64)
        cov = aggregated_correlation_covariance(gains @ gains.T, var, n_targets)
    else:
        for k in range(n_targets):
            for axis in range(2):
                columns.append(2.0 * gains[:, k] * grads[:, k, axis])
        atom = np.ones(n_leds)
        cov = np.diag(4.0 * var * (gains**2).sum(axis=1) + 2.0 * n_targets * var**2)
    if not noise_power_known:
        columns.append(atom)
    jac = np.column_stack(columns)
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, jac)
    fisher = white.T @ white
    try:
        inverse = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        inverse = np.full_like(fisher, np.inf)
    coords = inverse[: 2 * n_targets, : 2 * n_targets]
    blocks = np.diag(coords).reshape(n_targets, 2).sum(axis=1)
    per_target = np.sqrt(np.where(blocks > 0, blocks, np.inf))
    return AggregatedBound(per_target=per_target, mean=float(per_target.mean()), covariance=coords)


# -- bounds with nuisance parameters ---------------------------------------------------------
# Step of the central differences of the diffuse gains, metres: the quadrature's relative
# noise (about 1e-4, docs/results/reflections.md) then perturbs the derivative by well under 1 %.
_DIFFUSE_STEP_M = 0.02


@dataclass(frozen=True)
class Nuisances:
    """Unknown parameters besides the positions, each with a Gaussian prior (sd) or known.

    Attributes
    ----------
    log_gain_sd : float or None
        Each target's log amplitude gain ``u_k`` (0 at the truth); None: gains known.
    log_scale_sd : float or None
        The common log POWER scale ``v`` of the measurement (the amplitudes carry
        ``e^(v/2)``); None: known. ``inf`` is a flat prior (no information).
    height_sd_m : float
        Each target's height around ``grid.receiver_height``; 0: known.
    tilt_sd : float
        Each of the two tangent components of each photodiode's normal (about radians of
        tilt along x and y); 0: flat and known. Moves the line-of-sight part only (the
        diffuse part's tilt dependence is neglected).
    led_log_amplitude_sd : float
        Each LED's log pilot amplitude; 0: known.
    led_half_power_sd_deg : float
        Each LED's half-power angle, degrees; 0: known. Moves the line-of-sight part only.
    """

    log_gain_sd: float | None = None
    log_scale_sd: float | None = None
    height_sd_m: float = 0.0
    tilt_sd: float = 0.0
    led_log_amplitude_sd: float = 0.0
    led_half_power_sd_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("log_gain_sd", "log_scale_sd"):
            value = getattr(self, name)
            if value is not None and not (value > 0):
                raise MeasurementError(f"{name} must be positive or None", field=name)
        for name in ("height_sd_m", "tilt_sd", "led_log_amplitude_sd", "led_half_power_sd_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise MeasurementError(f"{name} must be finite and >= 0", field=name)


def nuisance_crlb(
    layout: Layout,
    positions: FloatArray,
    noise_std: float,
    model: Model | Literal["terminals"] = "correlation",
    nuisances: Nuisances | None = None,
    *,
    noise_power_known: bool = False,
) -> AggregatedBound:
    """Hybrid (Bayesian in the nuisances) bound on the positions with nuisance parameters.

    Parameters
    ----------
    layout : Layout
        The room as it is; with ``room.reflectance`` the channel includes the first diffuse
        bounce (:func:`app.vlp.reflections.diffuse_gains`).
    positions : ndarray of shape (K, 2)
        True positions, metres (at ``grid.receiver_height``, photodiodes facing up).
    noise_std : float
        sigma of one amplitude's noise (amplitude units).
    model : {"correlation", "power", "terminals"}, default="correlation"
        The aggregated forms (as :func:`aggregated_crlb`) or each terminal's own M
        amplitudes (``a_k = g_k + n_k``, sigma^2 I), all K terminals in one joint bound
        (they share the common scale and the LEDs).
    nuisances : Nuisances, default=None
        None: none (then equal to :func:`aggregated_crlb`, or per terminal to
        :func:`single_target_crlb`).
    noise_power_known : bool, default=False
        Aggregated forms: whether the noise atom's coefficient is known.

    Returns
    -------
    AggregatedBound

    Notes
    -----
    Amplitudes ``A_ik = x_i e^(l_i) e^(u_k + v/2) (h_los(p_k, z_k, n_k; m_i) + h_dif(p_k,
    z_k))`` with the nuisances at their true values 0 (heights at the receivers' plane,
    normals up, LEDs as in the layout). The Fisher information of all parameters is the
    data term ``J^T C^-1 J`` (``C`` as in :func:`aggregated_crlb`, ``sigma^2 I`` for
    terminals) plus each prior's ``1 / sd^2`` on its diagonal (Van Trees' Bayesian
    information for Gaussian priors, the data term taken at the true nuisances: the hybrid
    bound of Rockah and Schultheiss 1987). The positions' block of its inverse is the bound:
    it is what the nuisances cost an estimator that knows their priors. Line-of-sight
    derivatives are analytic; the diffuse part's are central differences with
    ``_DIFFUSE_STEP_M``.

    Examples
    --------
    >>> from app.vlp.presets import paper_layout
    >>> pts = np.array([[1.0, 1.0], [3.0, 2.5]])
    >>> plain = nuisance_crlb(paper_layout(), pts, 1e-6).mean
    >>> gains = nuisance_crlb(paper_layout(), pts, 1e-6, nuisances=Nuisances(log_gain_sd=0.1))
    >>> bool(gains.mean >= plain)
    True
    """
    _check_noise(noise_std)
    pts = _check_positions(layout, positions)
    if model not in ("power", "correlation", "terminals"):
        raise MeasurementError(
            f"model must be 'power', 'correlation' or 'terminals', got {model!r}", field="model"
        )
    nuis = nuisances or Nuisances()
    amplitudes, derivatives, prior = _amplitude_derivatives(layout, pts, nuis)
    var = noise_std**2
    n_leds, n_targets = amplitudes.shape
    if model == "terminals":
        jac = np.column_stack([d.T.ravel() for d in derivatives]) / noise_std
        data = jac.T @ jac
    else:
        columns = []
        if model == "correlation":
            row, col = np.triu_indices(n_leds)
            for d in derivatives:
                cross = d @ amplitudes.T
                columns.append((cross + cross.T)[row, col])
            atom = (row == col).astype(np.float64)
            cov = aggregated_correlation_covariance(amplitudes @ amplitudes.T, var, n_targets)
        else:
            for d in derivatives:
                columns.append(2.0 * (d * amplitudes).sum(axis=1))
            atom = np.ones(n_leds)
            cov = np.diag(4.0 * var * (amplitudes**2).sum(axis=1) + 2.0 * n_targets * var**2)
        if not noise_power_known:
            columns.append(atom)
            prior = np.append(prior, 0.0)
        white = np.linalg.solve(np.linalg.cholesky(cov), np.column_stack(columns))
        data = white.T @ white
    fisher = data + np.diag(prior)
    coords = _inverse(fisher)[: 2 * n_targets, : 2 * n_targets]
    blocks = np.diag(coords).reshape(n_targets, 2).sum(axis=1)
    per_target = np.sqrt(np.where(blocks > 0, blocks, np.inf))
    return AggregatedBound(per_target=per_target, mean=float(per_target.mean()), covariance=coords)


def _inverse(fisher: FloatArray) -> FloatArray:
    """Inverse of a symmetric information matrix, equilibrated (parameters differ in units)."""
    scale = np.sqrt(np.clip(np.diag(fisher), 1e-300, None))
    unit = fisher / np.outer(scale, scale)
    try:
        inverse = np.linalg.inv(unit)
    except np.linalg.LinAlgError:
        return np.full_like(fisher, np.inf)
    if np.linalg.cond(unit) > 1e14:
        return np.full_like(fisher, np.inf)
    return np.asarray(inverse / np.outer(scale, scale))


def _amplitude_derivatives(
    layout: Layout, pts: FloatArray, nuis: Nuisances
) -> tuple[FloatArray, list[FloatArray], FloatArray]:
    """``A`` (M, K), ``dA / d theta_j`` (M, K) per parameter, and the prior information
    ``1 / sd^2`` of each (0 for the positions), parameters in the order x1, y1, ..., xK, yK,
    then the nuisances that are unknown."""
    n_leds, n_targets = layout.n_leds, pts.shape[0]
    z0 = layout.grid.receiver_height
    xyz = np.column_stack((pts, np.full(n_targets, z0)))
    los, los_grad = los_gain_gradients(layout, xyz)  # (M, K), (M, K, 3)
    pilots = layout.pilot_amplitudes[:, None]
    diffuse = np.zeros_like(los)
    diffuse_grad = np.zeros_like(los_grad)
    if layout.room.reflectance is not None:
        diffuse = diffuse_gains(layout, xyz)
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = _DIFFUSE_STEP_M
            upper = _inside(layout, xyz + step)
            lower = _inside(layout, xyz - step)
            span = (upper - lower)[:, axis]
            diffuse_grad[:, :, axis] = (
                diffuse_gains(layout, upper) - diffuse_gains(layout, lower)
            ) / span[None, :]
    amplitudes = pilots * (los + diffuse)
    grads = pilots[:, :, None] * (los_grad + diffuse_grad)  # (M, K, 3)
    derivatives: list[FloatArray] = []
    prior: list[float] = []

    def one_target(k: int, column: FloatArray) -> FloatArray:
        out = np.zeros((n_leds, n_targets))
        out[:, k] = column
        return out

    for k in range(n_targets):
        for axis in range(2):
            derivatives.append(one_target(k, grads[:, k, axis]))
            prior.append(0.0)
    if nuis.height_sd_m > 0:
        for k in range(n_targets):
            derivatives.append(one_target(k, grads[:, k, 2]))
            prior.append(nuis.height_sd_m**-2)
    if nuis.tilt_sd > 0:
        # n = (t_x, t_y, 1) / |.|: d cos(phi) / d t at t = 0 is u_xy / d, so the line of sight
        # moves by h u_xy / u_z (u = LED minus receiver).
        to_led = layout.led_positions[:, None, :] - xyz[None, :, :]
        safe = np.where(los > 0, to_led[:, :, 2], 1.0)
        for k in range(n_targets):
            for axis in range(2):
                column = pilots[:, 0] * los[:, k] * to_led[:, k, axis] / safe[:, k]
                derivatives.append(one_target(k, column))
                prior.append(nuis.tilt_sd**-2)
    if nuis.log_gain_sd is not None:
        for k in range(n_targets):
            derivatives.append(one_target(k, amplitudes[:, k]))
            prior.append(nuis.log_gain_sd**-2)
    if nuis.log_scale_sd is not None:
        derivatives.append(0.5 * amplitudes)
        prior.append(0.0 if np.isinf(nuis.log_scale_sd) else nuis.log_scale_sd**-2)
    if nuis.led_log_amplitude_sd > 0:
        for i in range(n_leds):
            row = np.zeros((n_leds, n_targets))
            row[i] = amplitudes[i]
            derivatives.append(row)
            prior.append(nuis.led_log_amplitude_sd**-2)
    if nuis.led_half_power_sd_deg > 0:
        orders = np.atleast_1d(lambertian_order(layout.half_power_angles_deg))
        angles = np.radians(layout.half_power_angles_deg)
        # m = -ln 2 / ln cos(psi): dm / dpsi per degree.
        dm_dpsi = -math.log(2.0) * np.tan(angles) / np.log(np.cos(angles)) ** 2 * math.pi / 180
        cos_alpha = np.clip(
            (layout.led_positions[:, 2:3] - z0) / _distances(layout, xyz), 1e-300, 1
        )
        for i in range(n_leds):
            row = np.zeros((n_leds, n_targets))
            dh_dm = los[i] * (1.0 / (orders[i] + 1.0) + np.log(cos_alpha[i]))
            row[i] = pilots[i, 0] * dh_dm * dm_dpsi[i]
            derivatives.append(row)
            prior.append(nuis.led_half_power_sd_deg**-2)
    return amplitudes, derivatives, np.array(prior)


def _distances(layout: Layout, xyz: FloatArray) -> FloatArray:
    offsets = layout.led_positions[:, None, :] - xyz[None, :, :]
    return np.asarray(np.sqrt(np.einsum("mkc,mkc->mk", offsets, offsets)))


def _inside(layout: Layout, xyz: FloatArray) -> FloatArray:
    """Points clipped into the room (a central difference at a wall becomes one-sided)."""
    upper = np.array([layout.room.length, layout.room.width, layout.room.height])
    return np.asarray(np.clip(xyz, 1e-4, upper - 1e-4))
