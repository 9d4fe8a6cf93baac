"""Cramér-Rao lower bounds on the position error (the physical floor of any solver).

Two bounds:

- :func:`single_target_crlb`: one terminal, its own amplitudes ``a_i = g_i(p) + n_i``
  (``g_i = h_i x_i``, ``n_i ~ N(0, sigma^2)`` i.i.d.).
- :func:`aggregated_crlb`: K terminals seen only through the aggregated measurement
  (``vech(R)`` or ``p``), all 2K coordinates jointly, with the Gaussian approximation of the
  aggregated noise (exact first and second moments).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._typing import FloatArray
from .channel import channel_gain_gradients
from .errors import GeometryError, MeasurementError
from .layout import Layout
from .measurements import Model

__all__ = [
    "AggregatedBound",
    "aggregated_correlation_covariance",
    "aggregated_crlb",
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

    the issue's expression, where ``SNR_i`` is the link SNR at ``p``. In our SNR convention
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
